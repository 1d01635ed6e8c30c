"""Simulating a scenario file into a bag and its two sidecar files.

Three outputs, each written atomically (temporary name, then rename):

* ``BAG/`` -- a rosbag2 folder per the data contract: ``/tetra/mag1..4`` (MagneticField,
  tesla, body frame, header stamp = sample time), ``/odom``, ``/tetra/temperature``,
  ``/battery_state``;
* ``BAG.params.yaml`` -- beside the folder (not inside: a rosbag2 folder belongs to its
  storage): ``/**: ros__parameters:`` with ``sensor_positions`` (12 floats, m) and
  ``earth_field_enu`` (3 floats, T);
* ``BAG.truth.npz`` -- beside the folder: ``stamps_ns`` (N,) int64 (the header stamps),
  ``t_s`` (N,) s from the first sample, ``g_true`` (N, 3, 3) T/m (eq. 7 on the clean,
  noise-free fields: the compensation target), ``g_analytic`` (N, 3, 3) T/m (the exact
  gradient at the array centroid), ``segment`` (N,) index into the scenario's segments,
  ``segment_kind`` (S,) 'trim' / 'line', ``b_background`` (N, 3) T (true field at sensor 1,
  body frame), ``k_soft`` (4, 3, 3) and ``b_hard`` (4, 3) T (the per-sensor interference),
  ``k_effective`` (3, 3, 3) and ``b_effective`` (3, 3) T (the exact parameters of eq. 18 for
  ``B^b = B_1'``), ``noise_t``, ``sample_rate_hz``, ``seed``.
"""

from __future__ import annotations

import os
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import numpy.typing as npt

from ..core import MissionData, Scenario, TrimManoeuvre, simulate
from ..io.outputs import BAG, PARAMS, TRUTH, atomic_output, check_output
from ..io.params import params_document
from ..io.recording import mission_stamps_ns, write_mission_bag
from ..io.scenario import load_scenario

__all__ = ['SimulatedBag', 'sidecar_paths', 'simulate_to_bag']

PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class SimulatedBag:
    """What :func:`simulate_to_bag` wrote.

    Attributes
    ----------
    bag, params, truth : the bag folder and its two sidecar files
    scenario : Scenario
        The scenario flown.
    seed : int
        The seed of the simulation's random draws.
    mission : MissionData
        The simulated samples.
    """

    bag: Path
    params: Path
    truth: Path
    scenario: Scenario
    seed: int
    mission: MissionData


def sidecar_paths(bag: PathLike) -> tuple[Path, Path]:
    """``(BAG.params.yaml, BAG.truth.npz)`` beside the bag folder ``BAG``."""
    bag = Path(bag)
    return bag.with_name(bag.name + '.params.yaml'), bag.with_name(bag.name + '.truth.npz')


def simulate_to_bag(
    scenario_path: PathLike,
    out: PathLike,
    *,
    seed: int | None = None,
    start_ns: int,
    storage: str = 'sqlite3',
    mag_only: bool = False,
    progress: bool | None = None,
    force: bool = False,
) -> SimulatedBag:
    """Fly the scenario file ``scenario_path`` and write the bag ``out`` and its sidecars.

    Parameters
    ----------
    scenario_path : scenario YAML (:mod:`tetra_gradiometer.io.scenario`)
    out : the rosbag2 folder to write; the sidecars go beside it (:func:`sidecar_paths`)
    seed : overrides the scenario's seed
    start_ns : header stamp of the first sample, ns since the epoch
    storage : 'sqlite3' or 'mcap'
    mag_only : write only ``/tetra/mag1..4`` (no ``/odom``, temperature, battery)
    progress : tqdm bar on stderr (None: only on a terminal and for long missions)
    force : replace previous outputs of ours (anything else is refused before any work)

    Raises
    ------
    ScenarioError
        The scenario file is missing or invalid.
    OutputError
        An output is not ours to replace.
    """
    scenario, scenario_seed = load_scenario(scenario_path)
    seed = scenario_seed if seed is None else seed
    out = Path(out)
    params_path, truth_path = sidecar_paths(out)
    inputs = (scenario_path,)
    # Refuse before any work: nothing is simulated or written when an output is not ours.
    for path, kind in ((out, BAG), (params_path, PARAMS), (truth_path, TRUTH)):
        check_output(path, kind, force=force, inputs=inputs)
    mission = simulate(scenario, np.random.default_rng(seed))
    params = {
        'sensor_positions': scenario.geometry.to_flat(),
        'earth_field_enu': [float(v) for v in scenario.earth_field_enu],
    }
    # The sidecars are filled first and moved into place just after the bag: an interrupted
    # run leaves the three previous outputs, never a new bag beside old sidecars.
    with ExitStack() as stack:
        params_tmp = stack.enter_context(
            atomic_output(params_path, PARAMS, force=force, inputs=inputs)
        )
        params_tmp.write_text(
            '# Written by "python -m tetra_gradiometer simulate" from '
            f'{Path(scenario_path).name}\n' + params_document(params),
            encoding='utf-8',
        )
        truth_tmp = stack.enter_context(
            atomic_output(truth_path, TRUTH, force=force, inputs=inputs)
        )
        with open(truth_tmp, 'wb') as handle:
            _save_truth(handle, scenario, mission, mission_stamps_ns(mission, start_ns), seed)
        write_mission_bag(
            out,
            mission,
            start_ns=start_ns,
            storage=storage,
            odom=not mag_only,
            temperature=not mag_only,
            battery=not mag_only,
            progress=progress,
            force=force,
            inputs=inputs,
            command='simulate',
        )
    return SimulatedBag(out, params_path, truth_path, scenario, seed, mission)


def _save_truth(
    handle: BinaryIO,
    scenario: Scenario,
    mission: MissionData,
    stamps_ns: npt.NDArray[np.int64],
    seed: int,
) -> None:
    """Write the arrays of ``BAG.truth.npz`` (the module docstring lists them)."""
    effective = scenario.interference.effective_parameters()
    np.savez_compressed(
        handle,
        stamps_ns=stamps_ns,
        t_s=mission.t,
        g_true=mission.g_true,
        g_analytic=mission.g_analytic,
        segment=mission.segment.astype(np.int32),
        segment_kind=np.array(
            ['trim' if isinstance(s, TrimManoeuvre) else 'line' for s in scenario.segments]
        ),
        b_background=mission.b_background,
        k_soft=scenario.interference.k_soft,
        b_hard=scenario.interference.b_hard,
        k_effective=effective.k_soft,
        b_effective=effective.b_hard,
        noise_t=scenario.noise_t,
        sample_rate_hz=scenario.sample_rate_hz,
        seed=seed,
    )
