"""The paper's genetic algorithm (Yu et al. 2014, section 5), as printed.

Printed: binary coding, a 10-bit gene per variable, population 30, reproduction
probability 0.9, crossover 0.8, mutation 0.8, bounds of eq. 23. Not printed, our choices
(the conventions of the Sheffield GA toolbox, which these names and values follow):

* reproduction 0.9 = generation gap: 27 offspring per generation, chosen by stochastic
  universal sampling on linear ranking (selective pressure 2);
* crossover 0.8: single-point crossover of consecutive offspring pairs with probability 0.8;
* mutation 0.8: per offspring, probability 0.8 that one uniformly chosen bit flips (0.8
  per *bit* would make the search random);
* reinsertion by fitness: offspring replace the 27 worst parents, so the 3 best survive;
* 1000 generations (not printed), standard binary decoding over the closed bound interval.

A budget (not in the paper): ``deadline`` (a ``time.monotonic()`` instant) and ``should_stop``
(a callable, e.g. a service's cancel flag) are checked once per generation, before its
draws; when either ends the run, the best individual so far is returned and ``details``
say so (``stopped``: ``'deadline'`` or ``'should_stop'``, ``generations`` run of
``generations_requested``). Without a budget, or when it is not reached, the random draws
and the result are exactly those of the unbudgeted run.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from ..geometry import TetraGeometry
from ..model import InterferenceParameters
from ..types import ArrayLike, FloatArray
from ._linear import solve_scaled
from .lstsq import _check_samples, constraint_objective, paper_bounds
from .result import TensorCalibration

POPULATION = 30
GENE_BITS = 10
GENERATION_GAP = 0.9
CROSSOVER_PROBABILITY = 0.8
MUTATION_PROBABILITY = 0.8
GENERATIONS = 1000


def _decode(chromosomes: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> FloatArray:
    """(M, P*bits) bits -> (M, P) values in [lower, upper]."""
    m, n_par = len(chromosomes), len(lower)
    weights = 2 ** np.arange(GENE_BITS - 1, -1, -1)
    integers = chromosomes.reshape(m, n_par, GENE_BITS) @ weights
    return lower + (upper - lower) * integers / (2**GENE_BITS - 1)


def _ranking_fitness(objective: np.ndarray) -> FloatArray:
    """Linear ranking, selective pressure 2: best (lowest objective) 2, worst 0."""
    order = np.argsort(-objective, kind='stable')  # worst first
    fitness = np.empty_like(objective)
    fitness[order] = 2.0 * np.arange(len(objective)) / (len(objective) - 1)
    return fitness


def _sus(fitness: np.ndarray, count: int, rng: np.random.Generator) -> FloatArray:
    """Stochastic universal sampling: ``count`` indices, shuffled."""
    cumulative = np.cumsum(fitness)
    step = cumulative[-1] / count
    pointers = rng.uniform(0.0, step) + step * np.arange(count)
    chosen = np.searchsorted(cumulative, pointers, side='right')
    return rng.permutation(np.minimum(chosen, len(fitness) - 1))


def _offspring(
    population: npt.NDArray[np.int8],
    scores: npt.NDArray[np.float64],
    n_offspring: int,
    rng: np.random.Generator,
) -> npt.NDArray[np.int8]:
    """One generation's offspring: SUS on ranking fitness, one-point crossover, bit flips."""
    length = population.shape[1]
    offspring = population[_sus(_ranking_fitness(scores), n_offspring, rng)].copy()
    for first in range(0, n_offspring - 1, 2):
        if rng.random() < CROSSOVER_PROBABILITY:
            cut = rng.integers(1, length)
            tail = offspring[first, cut:].copy()
            offspring[first, cut:] = offspring[first + 1, cut:]
            offspring[first + 1, cut:] = tail
    mutate = np.flatnonzero(rng.random(n_offspring) < MUTATION_PROBABILITY)
    offspring[mutate, rng.integers(0, length, size=len(mutate))] ^= 1
    return offspring


def _stop_reason(deadline: float | None, should_stop: Callable[[], bool] | None) -> str | None:
    """Why the next generation must not start (``'should_stop'``, ``'deadline'``), or None."""
    if should_stop is not None and should_stop():
        return 'should_stop'
    if deadline is not None and time.monotonic() >= deadline:
        return 'deadline'
    return None


def _evolve(
    population: npt.NDArray[np.int8],
    scores: npt.NDArray[np.float64],
    objective: Callable[[npt.NDArray[np.int8]], FloatArray],
    generations: int,
    rng: np.random.Generator,
    deadline: float | None,
    should_stop: Callable[[], bool] | None,
) -> tuple[list[float], int, str | None]:
    """Run the generations in place on ``population``/``scores``: the best objective after
    each (the initial one first), the generations run and why it stopped early (or None)."""
    n_offspring = int(round(GENERATION_GAP * POPULATION))
    history = [float(scores.min())]
    ran, stopped = 0, None
    while ran < generations:
        stopped = _stop_reason(deadline, should_stop)
        if stopped is not None:
            break
        offspring = _offspring(population, scores, n_offspring, rng)
        offspring_scores = objective(offspring)
        worst = np.argsort(scores)[POPULATION - n_offspring :]
        population[worst], scores[worst] = offspring, offspring_scores
        history.append(float(scores.min()))
        ran += 1
    return history, ran, stopped


def paper_ga(
    g_measured: ArrayLike,
    b_reference: ArrayLike,
    geometry: TetraGeometry,
    *,
    rng: np.random.Generator,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    wide_bounds: bool = False,
    generations: int = GENERATIONS,
    deadline: float | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> TensorCalibration:
    """Minimise ``F(k, b)`` (eqs. 21-23) with the paper's GA.

    Parameters
    ----------
    g_measured : array_like, shape (N, 3, 3)
        Measured tensor, T/m.
    b_reference : array_like, shape (N, 3)
        ``B_1'``, tesla.
    geometry : TetraGeometry
    rng : numpy.random.Generator
        All randomness comes from here.
    bounds : (lower, upper), each shape (27,), optional
        SI; default :func:`~tetra_gradiometer.core.identification.paper_bounds`.
    wide_bounds : bool
        Use ``paper_bounds(wide=True)`` when ``bounds`` is not given.
    generations : int
    deadline : float, optional
        ``time.monotonic()`` instant after which no further generation starts.
    should_stop : callable, optional
        Asked once per generation; True ends the run (cancellation).

    Returns
    -------
    TensorCalibration
        ``details`` holds the initial and final objective (T/m)^2, the generations run and,
        when the budget ended the run early, ``stopped`` and ``generations_requested``.
    """
    design, target = constraint_objective(g_measured, b_reference, geometry, symmetric_k=True)
    _check_samples(len(target) // 4, 'paper_ga')
    lower, upper = bounds if bounds is not None else paper_bounds(symmetric=True, wide=wide_bounds)
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    n_par = design.shape[1]
    # F(theta) = (theta - theta*)^T Q (theta - theta*) + F(theta*): the same F as eq. 22,
    # evaluated around a least-squares point so that large F values do not cancel.
    exact = solve_scaled(design, target)
    gram = design.T @ design
    floor = float(exact.residual @ exact.residual)

    def objective(chromosomes: npt.NDArray[np.int8]) -> FloatArray:
        delta = _decode(chromosomes, lower, upper) - exact.theta
        return np.einsum('mp,pq,mq->m', delta, gram, delta) + floor

    population = rng.integers(0, 2, size=(POPULATION, n_par * GENE_BITS), dtype=np.int8)
    scores = objective(population)
    history, ran, stopped = _evolve(
        population, scores, objective, generations, rng, deadline, should_stop
    )
    best = int(np.argmin(scores))
    theta = _decode(population[best : best + 1], lower, upper)[0]
    budget = {'stopped': stopped, 'generations_requested': generations} if stopped else {}
    return TensorCalibration(
        method='paper_ga',
        n_samples=len(target) // 4,
        n_parameters=n_par,
        rank=exact.rank,
        condition_number=exact.condition_number,
        residual_rms=float(np.sqrt(scores[best] / len(target))),
        details={
            'objective_initial': history[0],
            'objective_final': float(scores[best]),
            'generations': ran,
            'wide_bounds': bool(wide_bounds and bounds is None),
            'objective_history': history[:: max(1, generations // 100)],
            **budget,
        },
        parameters=InterferenceParameters.from_vector(theta, symmetric=True),
        symmetric=True,
    )
