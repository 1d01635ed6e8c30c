"""``python -m tetra_gradiometer paper --out DIR``: reproduce section 6 of Yu et al. 2014.

The paper prints the interference (``K_1..K_4``, ``B_1^h..B_4^h``), the dipole moment, the
split of the pass (first 30 points identify, next 200 are compensated) and the metric
(eq. 24). Everything else is our choice and is written into ``results.json`` ("scenario")
and docs/paper.md. Two readings of the background field ``B^b`` are run:

* ``earth_field`` (top level of results.json): the dipole plus a 50 000 nT Earth field;
* ``dipole_only`` (under ``"scenarios"``): the dipole field alone, which is the reading
  that matches the paper's "hundreds of nT/m" of interference.

Methods: the paper's GA and the same objective solved exactly (``constraint_lstsq``), both on
the 30 identification points; ``known_gradient_lstsq`` with 27 (symmetric) and 36 (general)
parameters on a trim manoeuvre flown before the pass; ``pei_yeo_2009`` (reference [8]) on the
same 30 points as the paper's method, as the paper compared them.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core import (
    Dipole,
    InterferenceParameters,
    Scenario,
    SensorInterference,
    SurveyLine,
    TetraGeometry,
    TrimManoeuvre,
    difference_tensor,
    noise_floor,
    simulate,
    summarize,
)
from ..core.identification import METHODS as REGISTRY
from ..core.identification import (
    Options,
    TensorCalibration,
    constraint_lstsq,
    known_gradient_lstsq,
    paper_bounds,
    paper_ga,
    pei_yeo_2009,
)
from ..core.identification.paper_ga import (
    CROSSOVER_PROBABILITY,
    GENE_BITS,
    GENERATION_GAP,
    GENERATIONS,
    MUTATION_PROBABILITY,
    POPULATION,
)
from ..core.units import NT_PER_T
from ..errors import InputError
from ..io.outputs import PAPER, atomic_output, check_output

#: Section 6.1 as printed: soft iron K_1..K_4 (dimensionless) and hard iron B_1^h..B_4^h (nT).
PAPER_K = np.array(
    [
        [[0.05, 0.02, 0.03], [0.02, 0.01, 0.005], [0.03, 0.005, 0.02]],
        [[0.501, 0.0202, 0.0301], [0.0202, 0.1, 0.005], [0.0301, 0.005, 0.2]],
        [[0.5, 0.0202, 0.03], [0.0202, 0.101, 0.0051], [0.03, 0.0051, 0.2]],
        [[0.5, 0.02, 0.0303], [0.02, 0.1, 0.0051], [0.0303, 0.0051, 0.202]],
    ]
)
PAPER_B_HARD_NT = np.array(
    [[4.0, 6.0, 9.0], [13.0, -4.0, -6.0], [10.0, -5.0, 2.0], [-5.0, 11.0, 6.0]]
)
#: Section 6.2: the target's moment, A m^2 (we read "空间坐标系" as the world frame, ENU).
PAPER_MOMENT = (4.0e6, 0.0, 0.0)
#: Section 6.2, step 3: the paper's own estimates. ``k_hat`` is printed as (K_21 K_31 K_41),
#: 3 x 9 (each block symmetric); ``b_hat`` is printed with one row per pair, close to the true
#: B_i1^h = (9 -10 -15), (6 -11 -7), (-9 5 -3) nT - and outside its own bounds 0 <= b <= 10.
PAPER_K_HAT = np.array(
    [
        [0.00181, 0.00029, 0.00025, 0.00001, 0.00029, 0.0, 0.00002, 0.00001, 0.00038],
        [0.00029, 0.0, 0.00001, 0.00029, 0.00144, 0.00017, 0.00001, 0.0, 0.00017],
        [0.00025, 0.00001, 0.0, 0.0, 0.00017, 0.0, 0.00038, 0.00017, 0.00313],
    ]
)
PAPER_B_HAT_NT = np.array([[8.36, -9.23, -13.16], [6.31, -12.26, -7.35], [-8.89, 4.59, -2.54]])
N_IDENTIFY = 30
N_COMPENSATE = 200

#: Every registered method (the registry's order is the paper's comparison's).
METHODS = tuple(REGISTRY)
READINGS = ('earth_field', 'dipole_only')


@dataclass(frozen=True)
class Choices:
    """Everything the paper leaves open (SI unless named otherwise)."""

    edge_m: float = 0.5
    noise_nT: float = 0.1
    sample_rate_hz: float = 1.0
    # Target on the seabed; the pass is a straight, level line heading north at 50 m depth,
    # 50 m east of the target, so the closest approach is 50 sqrt(2) = 70.7 m, where the
    # dipole-only interference peaks at a few hundred nT/m (the paper's "hundreds of nT/m").
    dipole_position: tuple[float, float, float] = (0.0, 0.0, -100.0)
    line_east_m: float = 50.0
    line_depth_m: float = -50.0
    line_speed_m_s: float = 2.0
    closest_point_index: int = 130  # the closest approach is in the compensated part
    # Earth field: 50 000 nT, inclination 60 deg down, declination 0 (ENU: north and down).
    earth_intensity_nT: float = 50000.0
    earth_inclination_deg: float = 60.0
    earth_declination_deg: float = 0.0
    # Trim manoeuvre before the pass (the simulator's TrimManoeuvre: a circle with heading
    # turns, sinusoidal roll and pitch).
    trim_duration_s: float = 600.0
    trim_heading_rate_deg_s: float = 6.0
    trim_roll_amplitude_deg: float = 25.0
    trim_roll_period_s: float = 11.0
    trim_pitch_amplitude_deg: float = 20.0
    trim_pitch_period_s: float = 17.0
    trim_speed_m_s: float = 1.0
    # Earth-field reading: far from the target (3 km south), true gradient taken as zero.
    trim_center_far: tuple[float, float, float] = (0.0, -3000.0, -50.0)
    # Dipole-only reading: a uniform field is zero there, so the trim is flown near the
    # target and its true tensor is given to the solver.
    trim_center_near: tuple[float, float, float] = (50.0, 0.0, -50.0)
    seed: int = 20140611
    generations: int = GENERATIONS

    @property
    def earth_field_enu_t(self) -> np.ndarray:
        inc, dec = np.radians(self.earth_inclination_deg), np.radians(self.earth_declination_deg)
        horizontal = np.cos(inc)
        return (
            self.earth_intensity_nT
            / NT_PER_T
            * np.array([horizontal * np.sin(dec), horizontal * np.cos(dec), -np.sin(inc)])
        )

    @property
    def n_pass(self) -> int:
        return N_IDENTIFY + N_COMPENSATE

    def line(self) -> SurveyLine:
        spacing = self.line_speed_m_s / self.sample_rate_hz
        north0 = self.dipole_position[1] - spacing * self.closest_point_index
        length = spacing * self.n_pass  # exactly n_pass samples at the sample rate
        east = self.dipole_position[0] + self.line_east_m
        return SurveyLine(
            start=(east, north0, self.line_depth_m),
            end=(east, north0 + length, self.line_depth_m),
            speed_m_s=self.line_speed_m_s,
        )

    def trim(self, reading: str) -> TrimManoeuvre:
        return TrimManoeuvre(
            duration_s=self.trim_duration_s,
            center=self.trim_center_far if reading == 'earth_field' else self.trim_center_near,
            heading_rate_deg_s=self.trim_heading_rate_deg_s,
            roll_amplitude_deg=self.trim_roll_amplitude_deg,
            roll_period_s=self.trim_roll_period_s,
            pitch_amplitude_deg=self.trim_pitch_amplitude_deg,
            pitch_period_s=self.trim_pitch_period_s,
            speed_m_s=self.trim_speed_m_s,
        )

    def scenario(self, reading: str) -> Scenario:
        earth = self.earth_field_enu_t if reading == 'earth_field' else np.zeros(3)
        return Scenario(
            geometry=TetraGeometry.regular(self.edge_m),
            earth_field_enu=earth,
            segments=(self.trim(reading), self.line()),
            sample_rate_hz=self.sample_rate_hz,
            dipoles=(Dipole(self.dipole_position, PAPER_MOMENT),),
            interference=SensorInterference(PAPER_K, PAPER_B_HARD_NT / NT_PER_T),
            noise_t=self.noise_nT / NT_PER_T,
        )


@dataclass
class Reading:
    """One reading's results, in the results.json form."""

    scenario: dict
    identifiability: dict
    methods: dict
    variants: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    curves: dict = field(default_factory=dict)  # for the figures, nT/m, not written to JSON

    def as_json(self) -> dict:
        return {
            'scenario': self.scenario,
            'identifiability': self.identifiability,
            'methods': self.methods,
            'variants': self.variants,
            'diagnostics': self.diagnostics,
        }


def _timed(function, *args, **kwargs):
    start = time.perf_counter()
    result = function(*args, **kwargs)
    return result, time.perf_counter() - start


def _norms(g: np.ndarray) -> np.ndarray:
    return np.linalg.norm(g, axis=(1, 2)) * NT_PER_T


def run_reading(choices: Choices, reading: str) -> Reading:
    """Simulate one reading, identify with every method, compensate and score."""
    if reading not in READINGS:
        raise InputError(f'unknown reading {reading!r}; expected one of {READINGS}')
    scenario = choices.scenario(reading)
    geometry = scenario.geometry
    rng = np.random.default_rng([choices.seed, READINGS.index(reading)])
    data = simulate(scenario, rng)
    trim, line = data.select(data.segment == 0), data.select(data.segment == 1)
    if len(line) != choices.n_pass:
        raise RuntimeError(f'the pass has {len(line)} samples, expected {choices.n_pass}')
    ident, comp = line.select(slice(0, N_IDENTIFY)), line.select(slice(N_IDENTIFY, choices.n_pass))

    def measured(part):
        return difference_tensor(part.fields_measured, geometry), part.fields_measured[:, 0, :]

    g_ident, b_ident = measured(ident)
    g_trim, b_trim = measured(trim)
    g_before = difference_tensor(comp.fields_measured, geometry)
    trim_truth = None if reading == 'earth_field' else trim.g_true

    # Each registered method on the data the paper compares it on (docs/paper.md): the known-
    # gradient solves on the trim manoeuvre, the others on the first 30 pass points.
    on_trim = {'known_gradient_lstsq', 'known_gradient_lstsq_general'}
    calibrations, seconds = {}, {}
    for name in METHODS:
        part, g, b = (trim, g_trim, b_trim) if name in on_trim else (ident, g_ident, b_ident)
        options = Options(
            rng=np.random.default_rng([choices.seed, 7]),
            generations=choices.generations,
            g_true=trim_truth if name in on_trim else None,
            fields_measured=part.fields_measured,
        )
        calibrations[name], seconds[name] = _timed(REGISTRY[name].solve, g, b, geometry, options)
    variants_cal, variants_s = {}, {}
    variants_cal['paper_ga_wide_bounds'], variants_s['paper_ga_wide_bounds'] = _timed(
        paper_ga,
        g_ident,
        b_ident,
        geometry,
        rng=np.random.default_rng([choices.seed, 8]),
        wide_bounds=True,
        generations=choices.generations,
    )
    variants_cal['constraint_lstsq_paper_bounds'], variants_s['constraint_lstsq_paper_bounds'] = (
        _timed(constraint_lstsq, g_ident, b_ident, geometry, bounds=paper_bounds())
    )
    variants_cal['pei_yeo_2009_on_trim'], variants_s['pei_yeo_2009_on_trim'] = _timed(
        pei_yeo_2009, trim.fields_measured, geometry=geometry, g_true=trim_truth
    )

    if reading == 'dipole_only':
        # What a survey would really know near a target: the analytic gradient at the centroid,
        # which misses the differencing truncation (~ d/R) that g_true contains.
        name = 'known_gradient_lstsq_general_analytic_truth'
        variants_cal[name], variants_s[name] = _timed(
            known_gradient_lstsq,
            g_trim,
            b_trim,
            geometry,
            g_true=trim.g_analytic,
            symmetric_k=False,
        )
    variants_cal['paper_printed_estimate'] = TensorCalibration(
        method='paper_printed_estimate',
        n_samples=0,
        n_parameters=27,
        rank=0,
        condition_number=float('nan'),
        residual_rms=float('nan'),
        parameters=paper_printed_parameters(),
    )
    variants_s['paper_printed_estimate'] = 0.0

    def score(calibrations_, seconds_):
        out, after = {}, {}
        for name, calibration in calibrations_.items():
            after[name] = calibration.compensate_fields(comp.fields_measured, geometry)
            out[name] = {
                **summarize(g_before, after[name], comp.g_true),
                'solve_seconds': float(seconds_[name]),
            }
        return out, after

    methods, after = score(calibrations, seconds)
    variants, after_variants = score(variants_cal, variants_s)
    constraint = calibrations['constraint_lstsq']
    floor = noise_floor(scenario.noise_t, geometry) * NT_PER_T
    interference = g_before - comp.g_true
    diagnostics = {
        name: _diagnostics(cal) for name, cal in {**calibrations, **variants_cal}.items()
    }
    diagnostics['constraint_lstsq']['null_space_dim'] = constraint.null_space_dim
    curves = {
        'index': np.arange(N_IDENTIFY, choices.n_pass),
        'before': _norms(g_before),
        'error_before': _norms(interference),
        'true': _norms(comp.g_true),
        'after': {name: _norms(g) for name, g in {**after, **after_variants}.items()},
        'error': {
            name: _norms(g - comp.g_true) for name, g in {**after, **after_variants}.items()
        },
        'floor': floor,
    }
    return Reading(
        scenario=_describe(
            choices, reading, scenario, data, trim, line, comp, floor, interference
        ),
        identifiability={
            'constraint_rank': int(constraint.rank),
            'n_parameters': int(constraint.n_parameters),
        },
        methods=methods,
        variants=variants,
        diagnostics=diagnostics,
        curves=curves,
    )


def paper_printed_parameters() -> InterferenceParameters:
    """The paper's printed estimate (section 6.2, step 3) as parameters, SI."""
    k_soft = PAPER_K_HAT.reshape(3, 3, 3).transpose(1, 0, 2)  # block i = columns 3i..3i+2
    return InterferenceParameters(k_soft, PAPER_B_HAT_NT / NT_PER_T)


def _diagnostics(calibration) -> dict:
    if calibration.method == 'paper_printed_estimate':
        return {
            'method': calibration.method,
            'note': 'k_hat, b_hat as printed in the paper, applied by eq. 19',
        }
    return {k: v for k, v in calibration.summary().items() if k != 'objective_history'}


def _describe(
    choices: Choices,
    reading: str,
    scenario: Scenario,
    data,
    trim,
    line,
    comp,
    floor: float,
    interference: np.ndarray,
) -> dict:
    """Every choice the paper leaves open, plus the figures that characterise the data."""
    line_segment, trim_segment = scenario.segments[1], scenario.segments[0]
    dipole = np.asarray(choices.dipole_position)
    distance = np.linalg.norm(line.position_enu - dipole, axis=1)
    trim_distance = np.linalg.norm(trim.position_enu - dipole, axis=1)
    truncation = comp.g_analytic - comp.g_true
    return {
        'reading': reading,
        'background_field': (
            'dipole field only: B^b is the dipole field at sensor 1 (earth_field_enu = 0)'
            if reading == 'dipole_only'
            else 'dipole field plus a uniform 50 000 nT Earth field: B^b is the total field at sensor 1'
        ),
        'interference': 'K_1..K_4 and B_1^h..B_4^h as printed in section 6.1, applied per sensor by eq. 10 '
        'with B^b = the true (clean) field at sensor 1; sensor 1 is NOT clean (K_1 = 0.05 on '
        'the diagonal), so the exact parameters are K_i1 (I + K_1)^-1, not symmetric',
        'k_soft': PAPER_K.tolist(),
        'b_hard_nT': PAPER_B_HARD_NT.tolist(),
        'geometry': f'regular tetrahedron, edge {choices.edge_m} m, sensor 1 at the body origin, base in the '
        'body x-y plane, apex up (TetraGeometry.regular)',
        'sensor_positions_m': scenario.geometry.positions.tolist(),
        'noise_nT_per_axis': choices.noise_nT,
        'noise_floor_nT_per_m': floor,
        'sample_rate_hz': choices.sample_rate_hz,
        'seed': choices.seed,
        'dipole': {
            'moment_A_m2': list(PAPER_MOMENT),
            'position_enu_m': list(choices.dipole_position),
            'frame': 'world ENU (x east, y north, z up)',
        },
        'earth_field_enu_nT': (scenario.earth_field_enu * NT_PER_T).tolist(),
        'earth_field': (
            f'{choices.earth_intensity_nT:g} nT, inclination {choices.earth_inclination_deg:g} deg '
            f'(down), declination {choices.earth_declination_deg:g} deg'
            if reading == 'earth_field'
            else 'none'
        ),
        'survey_line': {
            'start_enu_m': list(line_segment.start),
            'end_enu_m': list(line_segment.end),
            'speed_m_s': line_segment.speed_m_s,
            'heading': 'north, level, no sway',
            'n_points': len(line),
            'spacing_m': choices.line_speed_m_s / choices.sample_rate_hz,
            'closest_approach_m': float(distance.min()),
            'closest_approach_index': int(np.argmin(distance)),
            'identification_points': [0, N_IDENTIFY - 1],
            'compensated_points': [N_IDENTIFY, len(line) - 1],
            'range_at_identification_m': [
                float(distance[:N_IDENTIFY].min()),
                float(distance[:N_IDENTIFY].max()),
            ],
        },
        'trim_manoeuvre': {
            'when': 'flown before the pass (segment 0); position jumps between segments',
            'center_enu_m': list(trim_segment.center),
            'duration_s': trim_segment.duration_s,
            'n_samples': len(trim),
            'heading_rate_deg_s': trim_segment.heading_rate_deg_s,
            'heading_turns': trim_segment.duration_s * trim_segment.heading_rate_deg_s / 360.0,
            'roll_amplitude_deg': trim_segment.roll_amplitude_deg,
            'roll_period_s': trim_segment.roll_period_s,
            'pitch_amplitude_deg': trim_segment.pitch_amplitude_deg,
            'pitch_period_s': trim_segment.pitch_period_s,
            'speed_m_s': trim_segment.speed_m_s,
            'circle_radius_m': trim_segment.speed_m_s
            / np.radians(trim_segment.heading_rate_deg_s),
            'range_to_dipole_m': [float(trim_distance.min()), float(trim_distance.max())],
            'max_true_gradient_nT_per_m': float(np.abs(trim.g_true).max() * NT_PER_T),
            'truth_given_to_solvers': (
                'none: the true gradient is taken as zero (uniform field far from the target)'
                if reading == 'earth_field'
                else 'the simulator g_true (eq. 7 on the clean fields) on the trim samples: in a '
                'dipole-only world a uniform field is zero, so a trim far away carries no '
                'information; flown near the target, its true tensor must be known'
            ),
        },
        'data_per_method': {
            'paper_ga': f'first {N_IDENTIFY} pass points, constraints of eq. 21 only; bounds of eq. 23 '
            f'(0 <= k <= 0.01, 0 <= b <= 10 nT); GA population {POPULATION}, {GENE_BITS}-bit genes, '
            f'generation gap {GENERATION_GAP}, crossover {CROSSOVER_PROBABILITY}, mutation '
            f'{MUTATION_PROBABILITY}, {choices.generations} generations',
            'constraint_lstsq': f'first {N_IDENTIFY} pass points, the objective of eqs. 21-22 solved exactly '
            '(minimum-norm in column-scaled coordinates, unbounded)',
            'known_gradient_lstsq': "trim manoeuvre, 27 parameters (symmetric K_i1, the paper's model)",
            'known_gradient_lstsq_general': 'trim manoeuvre, 36 parameters (general 3x3 K_i1)',
            'pei_yeo_2009': f'first {N_IDENTIFY} pass points, as the paper compares it on the same data as its '
            'own method; true sensor differences unknown there, taken as zero',
        },
        'variants': {
            'paper_ga_wide_bounds': 'paper_ga with |k| <= 1, |b| <= 1000 nT (the printed bounds exclude the truth)',
            'constraint_lstsq_paper_bounds': 'the eq. 21-22 objective solved exactly within the bounds of eq. 23',
            'pei_yeo_2009_on_trim': 'pei_yeo_2009 fitted on the trim manoeuvre (same data and truth as '
            'known_gradient_lstsq)',
            **(
                {
                    'known_gradient_lstsq_general_analytic_truth': 'known_gradient_lstsq_general on the trim given g_analytic (exact gradient at the centroid) '
                    'instead of g_true: includes the differencing truncation'
                }
                if reading == 'dipole_only'
                else {}
            ),
            'paper_printed_estimate': "no identification: the paper's printed k_hat, b_hat (section 6.2) "
            'applied by eq. 19 to our data',
        },
        'truth': 'g_true of the simulator: eq. 7 applied to the clean, noise-free fields (what a perfect '
        'instrument of this geometry reads); metrics over the 200 compensated points',
        'g_analytic_truncation': {
            'note': 'g_analytic (exact gradient at the array centroid) differs from g_true by the differencing '
            'truncation (~ d/R); it is not used as truth',
            'rms_nT_per_m': float(np.sqrt(np.mean(truncation**2)) * NT_PER_T),
            'max_abs_nT_per_m': float(np.abs(truncation).max() * NT_PER_T),
            'relative_rms': float(np.sqrt(np.mean(truncation**2) / np.mean(comp.g_true**2))),
        },
        'uncompensated': {
            'rms_interference_nT_per_m': float(np.sqrt(np.mean(interference**2)) * NT_PER_T),
            'max_interference_frobenius_nT_per_m': float(
                np.linalg.norm(interference, axis=(1, 2)).max() * NT_PER_T
            ),
            'max_true_frobenius_nT_per_m': float(
                np.linalg.norm(comp.g_true, axis=(1, 2)).max() * NT_PER_T
            ),
        },
    }


def reproduce(
    out_dir: str | Path, *, choices: Choices | None = None, plots: bool = True, force: bool = False
) -> dict:
    """Run both readings, write ``results.json`` (and the figures) into the folder ``out_dir``
    (atomically; a previous paper folder is replaced only with ``force``); return the JSON."""
    choices = choices or Choices()
    check_output(out_dir, PAPER, force=force)  # refuse before the work
    readings = {name: run_reading(choices, name) for name in READINGS}
    results = readings['earth_field'].as_json()
    results['scenarios'] = {'dipole_only': readings['dipole_only'].as_json()}
    with atomic_output(out_dir, PAPER, force=force, command='paper') as folder:
        folder.mkdir()
        (folder / 'results.json').write_text(
            json.dumps(results, indent=2, allow_nan=False) + '\n', encoding='utf-8'
        )
        if plots:
            for name, reading in readings.items():
                plot_fig2(reading, folder / f'fig2_{name}.png', TITLES[name])
                plot_fig3(reading, folder / f'fig3_{name}.png', TITLES[name])
    return results


TITLES = {'earth_field': 'dipole + 50 000 nT Earth field', 'dipole_only': 'dipole field only'}
FIGURES = tuple(f'fig{n}_{reading}.png' for n in (2, 3) for reading in READINGS)
COLOURS = {
    'paper_ga': 'tab:orange',
    'constraint_lstsq': 'tab:purple',
    'known_gradient_lstsq': 'tab:green',
    'known_gradient_lstsq_general': 'tab:blue',
    'pei_yeo_2009': 'tab:brown',
    'paper_ga_wide_bounds': 'tab:pink',
    'pei_yeo_2009_on_trim': 'tab:olive',
}


def _pyplot():
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def _floor_line(axis, curves: dict) -> None:
    # The Frobenius norm of pure sensor noise on the tensor is ~3x the per-component RMS.
    axis.axhline(
        3 * curves['floor'],
        color='grey',
        lw=1,
        ls=':',
        label=f'noise (Frobenius, 3 x {curves["floor"]:.2f})',
    )


def plot_fig2(reading: Reading, path: Path, title: str) -> None:
    """Analogue of Fig. 2: |G|_F before, after and true along the pass, per method."""
    plt = _pyplot()
    c = reading.curves
    figure, axes = plt.subplots(2, 2, figsize=(12, 7.5), sharex=True)
    for row, name in enumerate(('paper_ga', 'known_gradient_lstsq_general')):
        m = reading.methods[name]
        left, right = axes[row]
        left.semilogy(c['index'], c['before'], color='tab:red', lw=1.5, label='before (measured)')
        left.semilogy(c['index'], c['after'][name], color=COLOURS[name], lw=1.5, label='after')
        left.semilogy(c['index'], c['true'], color='k', lw=1.2, ls='--', label='true')
        left.set_ylabel('|G|_F  (nT/m)')
        left.set_title(
            f'{name}: {m["compensated_percent"]:.3f} % compensated (eq. 24)', fontsize=10
        )
        right.semilogy(
            c['index'],
            c['error_before'],
            color='tab:red',
            lw=1.0,
            alpha=0.7,
            label='before: |G_m - G_true|_F',
        )
        right.semilogy(c['index'], c['error'][name], color=COLOURS[name], lw=1.2, label='after')
        _floor_line(right, c)
        right.set_ylabel('|G_after - G_true|_F  (nT/m)')
        right.set_title(
            f'{name}: residual RMS {m["rms_residual_nT_per_m"]:.3g} nT/m per component',
            fontsize=10,
        )
        left.legend(fontsize=8, loc='best')
        right.legend(fontsize=8, loc='best')
        for axis in (left, right):
            axis.grid(True, which='both', alpha=0.3)
    for axis in axes[1]:
        axis.set_xlabel('pass point index (30-229 compensated; 2 m spacing)')
    figure.suptitle(f'Fig. 2 analogue, {title}: Frobenius norm along the pass')
    figure.tight_layout()
    figure.savefig(path, format='png', dpi=110)
    plt.close(figure)


def plot_fig3(reading: Reading, path: Path, title: str) -> None:
    """Analogue of Fig. 3: the methods compared along the pass."""
    plt = _pyplot()
    c = reading.curves
    figure, (left, right) = plt.subplots(1, 2, figsize=(13, 6.5))
    left.semilogy(c['index'], c['before'], color='tab:red', lw=2, label='before (measured)')
    right.semilogy(
        c['index'], c['error_before'], color='tab:red', lw=2, label='before (interference)'
    )
    for name in METHODS:
        m = reading.methods[name]
        label = f'{name} ({m["compensated_percent"]:.1f} %, {m["rms_residual_nT_per_m"]:.3g} nT/m)'
        left.semilogy(c['index'], c['after'][name], color=COLOURS[name], lw=1.2, label=label)
        right.semilogy(c['index'], c['error'][name], color=COLOURS[name], lw=1.2, label=name)
    left.semilogy(c['index'], c['true'], color='k', lw=1.5, ls='--', label='true')
    _floor_line(right, c)
    left.set_ylabel('|G|_F  (nT/m)')
    left.set_title('after compensation (legend: eq. 24 %, residual RMS)', fontsize=10)
    right.set_ylabel('|G_after - G_true|_F  (nT/m)')
    right.set_title('error of each method', fontsize=10)
    for axis in (left, right):
        axis.set_xlabel('pass point index (30-229 compensated; 2 m spacing)')
        axis.grid(True, which='both', alpha=0.3)
        axis.legend(
            fontsize=8, loc='upper center', bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False
        )
    figure.suptitle(f'Fig. 3 analogue, {title}: methods compared')
    figure.tight_layout()
    figure.savefig(path, format='png', dpi=110)
    plt.close(figure)


def format_table(reading: dict, title: str) -> str:
    """The methods table of one reading, as printed by the command."""
    floor = reading['scenario']['noise_floor_nT_per_m']
    rows = [
        f'{title}  (constraint rank {reading["identifiability"]["constraint_rank"]} of '
        f'{reading["identifiability"]["n_parameters"]}; noise floor {floor:.3f} nT/m; '
        f'uncompensated RMS {reading["scenario"]["uncompensated"]["rms_interference_nT_per_m"]:.4g} nT/m)',
        f'  {"method":<46} {"compensated %":>14} {"RMS nT/m":>12} {"improvement":>12} {"solve s":>9}',
    ]
    entries = list(reading['methods'].items()) + [
        (f'({name})', v) for name, v in reading['variants'].items()
    ]
    for name, m in entries:
        rows.append(
            f'  {name:<46} {m["compensated_percent"]:>14.3f} {m["rms_residual_nT_per_m"]:>12.4g} '
            f'{m["improvement_ratio"]:>12.4g} {m["solve_seconds"]:>9.4f}'
        )
    return '\n'.join(rows)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        '--out', required=True, help='output folder (results.json and PNG figures)'
    )
    parser.add_argument(
        '--generations',
        type=int,
        default=GENERATIONS,
        help=f'GA generations for paper_ga (default {GENERATIONS})',
    )
    parser.add_argument('--seed', type=int, default=Choices.seed, help='seed of every random draw')
    parser.add_argument('--no-plots', action='store_true', help='skip the PNG figures')
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace a previous paper folder at --out (anything else there is refused)',
    )


def run(args: argparse.Namespace) -> int:
    if args.generations < 1:
        raise InputError(f'--generations must be >= 1, got {args.generations}')
    choices = Choices(seed=args.seed, generations=args.generations)
    results = reproduce(args.out, choices=choices, plots=not args.no_plots, force=args.force)
    print(format_table(results, 'Earth-field reading (dipole + 50 000 nT)'))
    print()
    print(format_table(results['scenarios']['dipole_only'], 'Dipole-only reading'))
    print(f'\nwrote {Path(args.out) / "results.json"}')
    return 0
