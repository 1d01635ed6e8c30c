"""Time every identification solver on 30, 1 000 and 10 000 samples (``make bench``).

Data: a simulated trim manoeuvre (paper's interference of section 6.1, 50 000 nT Earth
field, 0.1 nT noise, regular 0.5 m tetrahedron) at 10 Hz for 1 000 s; each size takes
samples evenly spaced over the whole manoeuvre, so every size has full attitude coverage.
Every solver gets the same samples (the constraint methods do not need the truth; it is
zero here anyway). Times are the median of several calls, wall clock, on whatever the
machine is doing at the time: indicative only.

It also checks that ``known_gradient_lstsq`` (exact QR reduction to 4 pseudo-samples)
gives the same answer as the dense solve it replaced (the (N, 9, P) design and an SVD of
the 9N x P matrix, rebuilt here from the public pieces), to ~1e-9 relative.

    .venv/bin/python bench/bench_solvers.py [--sizes 30 1000 10000] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tetra_gradiometer.core import (Scenario, SensorInterference, TetraGeometry,  # noqa: E402
                                    TrimManoeuvre, difference_tensor, simulate)
from tetra_gradiometer.core.design import interference_design  # noqa: E402
from tetra_gradiometer.core.identification import (constraint_lstsq, known_gradient_lstsq,  # noqa: E402
                                                   paper_ga, pei_yeo_2009)
from tetra_gradiometer.core.identification._linear import solve_scaled  # noqa: E402
from tetra_gradiometer.core.identification.lstsq import noise_whitener  # noqa: E402
from tetra_gradiometer.core.paper import PAPER_B_HARD_NT, PAPER_K  # noqa: E402

TARGET_SECONDS = 0.050  # 27 parameters from 10 000 samples


def dense_known_gradient(g_measured, b_reference, geometry, *, symmetric_k):
    """The previous implementation: whitened (N, 9, P) design, SVD of the 9N x P matrix."""
    n = len(g_measured)
    whitener = noise_whitener(geometry)
    design = interference_design(b_reference, geometry, symmetric=symmetric_k)
    n_par = design.shape[2]
    design_w = np.einsum('nRjp,jk->nRkp', design.reshape(n, 3, 3, n_par), whitener).reshape(-1, n_par)
    target_w = (g_measured @ whitener).reshape(-1)
    solution = solve_scaled(design_w, target_w)
    sigma2 = float(solution.residual @ solution.residual) / max(target_w.size - solution.rank, 1)
    return solution, sigma2 * solution.covariance_unit


def median_seconds(function, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def make_data(n_total: int = 10_000, seed: int = 1):
    geometry = TetraGeometry.regular(0.5)
    scenario = Scenario(
        geometry=geometry, earth_field_enu=np.array([0.0, 25_000e-9, -43_301e-9]),
        segments=(TrimManoeuvre(duration_s=n_total / 10.0),), sample_rate_hz=10.0,
        interference=SensorInterference(PAPER_K, PAPER_B_HARD_NT * 1e-9), noise_t=0.1e-9)
    data = simulate(scenario, np.random.default_rng(seed))
    return geometry, data


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--sizes', type=int, nargs='+', default=[30, 1000, 10_000])
    parser.add_argument('--generations', type=int, default=1000, help='paper_ga generations')
    parser.add_argument('--json', help='also write the table to this JSON file')
    args = parser.parse_args(argv)
    geometry, data = make_data(max(10_000, max(args.sizes)))
    rows, checks = [], []
    for n in args.sizes:
        index = np.linspace(0, len(data) - 1, n).round().astype(int)
        fields = data.fields_measured[index]
        g, b = difference_tensor(fields, geometry), fields[:, 0, :]
        fast = 9 if n <= 1000 else 5
        solvers = {
            'known_gradient_lstsq (27)': (lambda: known_gradient_lstsq(g, b, geometry, symmetric_k=True), fast),
            'known_gradient_lstsq_general (36)': (
                lambda: known_gradient_lstsq(g, b, geometry, symmetric_k=False), fast),
            'constraint_lstsq (27)': (lambda: constraint_lstsq(g, b, geometry), fast),
            'pei_yeo_2009 (36)': (lambda: pei_yeo_2009(fields), fast),
            f'paper_ga (27, {args.generations} gen.)': (
                lambda: paper_ga(g, b, geometry, rng=np.random.default_rng(0), generations=args.generations), 3),
            'dense SVD solve only (27, previous)': (
                lambda: dense_known_gradient(g, b, geometry, symmetric_k=True), 3),
        }
        timings = {name: median_seconds(f, repeats) for name, (f, repeats) in solvers.items()}
        reference = timings['known_gradient_lstsq (27)']
        for name, seconds in timings.items():
            rows.append({'n_samples': n, 'solver': name, 'seconds': seconds, 'ratio': seconds / reference})
        for symmetric in (True, False):
            new = known_gradient_lstsq(g, b, geometry, symmetric_k=symmetric)
            old, old_covariance = dense_known_gradient(g, b, geometry, symmetric_k=symmetric)
            theta = new.parameters.to_vector(symmetric=symmetric)
            checks.append({
                'n_samples': n, 'parameters': 27 if symmetric else 36,
                'theta_rel': float(np.abs(theta - old.theta).max() / np.abs(old.theta).max()),
                'covariance_rel': float(np.abs(new.covariance - old_covariance).max()
                                        / np.abs(old_covariance).max()),
                'condition_rel': abs(new.condition_number - old.condition_number) / old.condition_number,
                'rank_equal': new.rank == old.rank,
            })
    print(f'bench_solvers: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, '
          f'numpy {np.__version__}; median wall-clock seconds; ratio to known_gradient_lstsq (27) '
          f'at the same size')
    print(f'  {"samples":>7}  {"solver":<42} {"seconds":>10} {"ratio":>9}')
    for row in rows:
        print(f'  {row["n_samples"]:>7}  {row["solver"]:<42} {row["seconds"]:>10.5f} {row["ratio"]:>9.2f}')
    print('\nfast vs dense solve of known_gradient_lstsq (max relative difference):')
    for c in checks:
        print(f'  {c["n_samples"]:>7} samples, {c["parameters"]} parameters: theta {c["theta_rel"]:.1e}, '
              f'covariance {c["covariance_rel"]:.1e}, condition {c["condition_rel"]:.1e}, '
              f'rank equal {c["rank_equal"]}')
    big = [r for r in rows if r['solver'] == 'known_gradient_lstsq (27)' and r['n_samples'] >= 10_000]
    ok = all(r['seconds'] < TARGET_SECONDS for r in big)
    agree = all(c['theta_rel'] < 1e-9 and c['covariance_rel'] < 1e-9 and c['rank_equal'] for c in checks)
    if big:
        print(f'\ntarget: 27 parameters from 10 000 samples in < {TARGET_SECONDS * 1e3:.0f} ms: '
              f'{"met" if ok else "NOT met"} ({big[0]["seconds"] * 1e3:.1f} ms)')
    print(f'fast solve agrees with the dense SVD to 1e-9: {"yes" if agree else "NO"}')
    if args.json:
        Path(args.json).write_text(json.dumps({'timings': rows, 'checks': checks}, indent=2) + '\n')
    return 0 if ok and agree else 1


if __name__ == '__main__':
    sys.exit(main())
