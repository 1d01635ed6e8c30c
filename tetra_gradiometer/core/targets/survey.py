"""From a survey's tensors to targets: detect, fit the strongest detection, take it out,
detect again (:func:`locate`); the passes of one target are fitted together.

Association: a new detection's fit is a known target when their positions are closer than
``associate_sigmas`` combined 1-sigma (root of the sum of the two position covariances'
traces, at most ``associate_max_sigma_m``) plus ``associate_floor_m``. A target's passes
are the windows of the legs where its predicted tensor exceeds ``footprint_sigmas`` noise
sigma (:func:`footprint`). A target is reported with its joint fit, the passes it was
seen on, and whether a point dipole explains it (``dipolar``: misfit fraction at most
``max_misfit`` or a reduced chi-square at most ``max_chi2``; a close pair or an extended
object fails both).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...errors import InputError
from .._distributions import chi2_isf, f_isf
from ..geometry import TetraGeometry, to_world
from ..types import FloatArray
from .detection import Detection, DetectionResult, DetectorSettings, detect
from .forward import array_tensor, symmetric_components
from .localization import DipoleFit, Pass, fit_dipole, fit_dipoles

#: Refits of every target after the last one is found (each moves the footprints), on
#: thinned passes; then one fit on every sample, alone or jointly with its cluster.
FINAL_SWEEPS = 2
#: While targets are being found, their fits take at most this many samples per pass.
SWEEP_SAMPLES = 300
#: Clusters of at most this many targets are fitted jointly (a larger one keeps its sweeps).
MAX_CLUSTER = 6
#: Targets whose predicted tensors correlate beyond this are fitted jointly (fitting each
#: with the other taken out leaves an error of about the square of it; a ghost of a
#: strong target's misfit correlates with it by a few percent).
COUPLING = 0.02


@dataclass(frozen=True)
class LocatorSettings:
    """How detections become targets (units in the names)."""

    detector: DetectorSettings = field(default_factory=DetectorSettings)
    #: The fit window: the detection's span widened by this fraction of its length per side.
    widen: float = 0.25
    associate_sigmas: float = 3.0
    associate_floor_m: float = 1.0
    associate_max_sigma_m: float = 2.0
    max_misfit: float = 0.05
    max_chi2: float = 3.0
    #: False-alarm probability of the test that a fit's moment is not zero.
    significance: float = 1e-6
    #: A target's passes: where its predicted tensor exceeds this many noise sigma.
    footprint_sigmas: float = 3.0
    #: At most this many targets (each one a round of fitting and detecting again).
    max_targets: int = 50


@dataclass(frozen=True)
class Target:
    """A located target: its joint ``fit`` and the ``detections`` it was seen in, with
    ``first_seen_s`` and ``last_seen_s`` (the track's times of its first and last
    detection sample), whether it is ``dipolar``, and ``fitted_with``: the indices (in
    :func:`locate`'s list) of the targets fitted jointly with it (their tensors overlap:
    a close pair or group; their estimates are correlated)."""

    fit: DipoleFit
    detections: list[Detection]
    first_seen_s: float
    last_seen_s: float
    dipolar: bool
    fitted_with: tuple[int, ...] = ()


@dataclass(frozen=True)
class Survey:
    """A track: times ``t_s`` (N,) s, body origin ``positions`` (N, 3) m in the odom frame,
    ``rotations`` (N, 3, 3) body -> odom, body-frame ``tensors`` (N, 3, 3) T/m."""

    t_s: FloatArray
    positions: FloatArray
    rotations: FloatArray
    tensors: FloatArray

    def piece(self, start: int, stop: int) -> Pass:
        return Pass(
            self.positions[start:stop],
            self.rotations[start:stop],
            self.tensors[start:stop],
            self.t_s[start:stop],
        )


def fit_window(detection: Detection, widen: float) -> tuple[int, int]:
    """The samples a detection is fitted on: its span widened by ``widen`` of its length on
    each side, within its leg."""
    margin = int(np.ceil(widen * (detection.stop - detection.start)))
    return max(detection.leg_start, detection.start - margin), min(
        detection.leg_stop, detection.stop + margin
    )


def locate(
    survey: Survey, geometry: TetraGeometry, settings: LocatorSettings | None = None
) -> tuple[list[Target], DetectionResult]:
    """Targets of ``survey`` (and the first detection result, on the survey's own tensors).

    CLEAN-style (Hogbom 1974, for point sources on a sky): fit the strongest detection,
    join it to a known target when the fit puts it there (then refit that target on all its
    passes), take every target's tensors out of the survey, detect again on what is left;
    until nothing is detected. A target's tensors are thus never found twice on the lines
    beside it, and a weak target's pass is fitted without its neighbours' tails. Last, each
    target is refitted on its passes with all the others taken out.

    Raises
    ------
    InputError
        Nothing to search (:func:`.detection.detect`).
    """
    settings = settings or LocatorSettings()
    if len(survey.t_s) < 10:
        raise InputError(f'a survey of {len(survey.t_s)} samples: too short to search')
    first = detect(
        survey.t_s, survey.tensors, survey.positions, survey.rotations, settings.detector
    )
    sigma = first.sigma
    catalogue = _Catalogue(survey, geometry, settings, first.legs)
    rejected: list[tuple[int, int]] = []
    found = first
    for _ in range(settings.max_targets):
        fresh = [d for d in found.detections if not any(a <= d.peak < b for a, b in rejected)]
        if not fresh:
            break
        detection = max(fresh, key=lambda d: d.peak_statistic)
        rejected.append((detection.start, detection.stop))  # fitted or refused: not again
        window = fit_window(detection, settings.widen)
        fit = fit_dipole([catalogue.cleaned(window, ())], geometry, sigma)
        if not significant(fit, settings.significance):
            continue
        k = catalogue.add(fit, detection)
        catalogue.sweep(sigma, [k], thin=True)  # its footprint, then who shares it
        catalogue.sweep(sigma, catalogue.neighbours(k), thin=True)
        residual = survey.tensors - catalogue.predicted(())
        found = detect(survey.t_s, residual, survey.positions, survey.rotations, settings.detector)
        sigma = found.sigma  # with the targets out, more of the survey is quiet
    for _ in range(FINAL_SWEEPS):
        catalogue.sweep(sigma, thin=True)
    for cluster in catalogue.clusters(sigma):  # the last fits take every sample
        if 2 <= len(cluster) <= MAX_CLUSTER:
            catalogue.resolve(cluster, sigma)
        else:
            catalogue.sweep(sigma, cluster)
    catalogue.drop_empty()
    return _targets(catalogue, settings), first


def _targets(catalogue: _Catalogue, settings: LocatorSettings) -> list[Target]:
    """The catalogue's targets in the order they were first seen."""
    t_s = catalogue.survey.t_s
    order = sorted(
        range(len(catalogue.fits)),
        key=lambda k: min(t_s[d.start] for d in catalogue.passes[k]),
    )
    rank = {k: i for i, k in enumerate(order)}
    targets = []
    for k in order:
        fit, detections = catalogue.fits[k], catalogue.passes[k]
        dipolar = (
            fit.misfit_fraction <= settings.max_misfit or fit.chi2_reduced <= settings.max_chi2
        )
        group = catalogue.groups[k]
        targets.append(
            Target(
                fit,
                detections,
                float(min(t_s[d.start] for d in detections)),
                float(max(t_s[d.stop - 1] for d in detections)),
                bool(dipolar),
                tuple(
                    sorted(
                        rank[j]
                        for j, other in enumerate(catalogue.groups)
                        if j != k and group >= 0 and other == group
                    )
                ),
            )
        )
    return targets


class _Catalogue:
    """The targets found so far: their fits, detections (``passes``) and footprints."""

    def __init__(
        self,
        survey: Survey,
        geometry: TetraGeometry,
        settings: LocatorSettings,
        legs: list[tuple[int, int]],
    ) -> None:
        self.survey, self.geometry, self.settings, self.legs = survey, geometry, settings, legs
        self.fits: list[DipoleFit] = []
        self.passes: list[list[Detection]] = []
        self.footprints: list[list[tuple[int, int]]] = []
        #: The joint fit each target is in (-1: fitted alone).
        self.groups: list[int] = []

    def add(self, fit: DipoleFit, detection: Detection) -> int:
        """A new target, or a new pass of the known target ``fit`` puts it at: its index."""
        k = _nearest(fit, self.fits, self.settings)
        if k is None:
            self.fits.append(fit)
            self.passes.append([])
            self.footprints.append([])
            self.groups.append(-1)
            k = len(self.fits) - 1
        self.passes[k].append(detection)
        self.footprints[k].append(fit_window(detection, self.settings.widen))
        return k

    def neighbours(self, k: int) -> list[int]:
        """Target ``k`` and those whose footprints share samples with its own."""
        return [
            j
            for j, windows in enumerate(self.footprints)
            if j == k or any(a < d and c < b for a, b in windows for c, d in self.footprints[k])
        ]

    def sweep(self, sigma: FloatArray, which: list[int] | None = None, thin: bool = False) -> None:
        """Targets ``which`` (default all) refitted on their footprints with the others
        taken out (Gauss-Seidel: a target found later corrects the fits of those whose
        windows it reaches). ``thin``: at most :data:`SWEEP_SAMPLES` samples per pass (the
        fits while targets are still being found; the last sweeps take every sample)."""
        for k in range(len(self.fits)) if which is None else which:
            fit = self.fits[k]
            # The target's passes: wherever its predicted tensor stands out of the noise
            # (none when the noise is far above it: then the windows it was found in).
            self.footprints[k] = footprint(
                self.survey, self.geometry, fit, sigma, self.legs, self.settings.footprint_sigmas
            ) or [fit_window(d, self.settings.widen) for d in self.passes[k]]
            pieces = [self.cleaned(window, (k,)) for window in self.footprints[k]]
            if thin:
                pieces = [piece.thinned(SWEEP_SAMPLES) for piece in pieces]
            self.fits[k] = fit_dipole(pieces, self.geometry, sigma, fit.position)

    def clusters(self, sigma: FloatArray) -> list[list[int]]:
        """The targets grouped by coupling (connected components): two targets are coupled
        when the correlation of their predicted whitened tensors, demeaned per window as the
        backgrounds demean them, exceeds :data:`COUPLING` where their footprints share
        samples (then fitting each with the other taken out converges slowly, or a ghost
        of one's misfit sits beside it)."""
        signals = [
            [self._signal(k, window, sigma) for window in self.footprints[k]]
            for k in range(len(self.fits))
        ]
        energy = [sum(float(np.sum(w**2)) for w in windows) for windows in signals]
        unseen = set(range(len(self.fits)))
        out = []
        while unseen:
            stack, cluster = [min(unseen)], []
            unseen.discard(stack[0])
            while stack:
                k = stack.pop()
                cluster.append(k)
                for j in self.neighbours(k):
                    if j in unseen and self._coupling(j, k, sigma, energy) > COUPLING:
                        unseen.discard(j)
                        stack.append(j)
            out.append(sorted(cluster))
        return out

    def _signal(self, k: int, window: tuple[int, int], sigma: FloatArray) -> FloatArray:
        """Target ``k``'s whitened five components (n, 5) over ``window``, demeaned."""
        piece = self.survey.piece(*window)
        fit = self.fits[k]
        tensors = array_tensor(
            piece.positions, piece.rotations, self.geometry, fit.position, fit.moment
        )
        whitened = symmetric_components(to_world(tensors, piece.rotations)) / sigma
        out: FloatArray = whitened - whitened.mean(axis=0)
        return out

    def _coupling(self, j: int, k: int, sigma: FloatArray, energy: list[float]) -> float:
        """|<s_j, s_k>| / (|s_j| |s_k|) over the samples both footprints hold."""
        cross = 0.0
        for a, b in self.footprints[j]:
            for c, d in self.footprints[k]:
                if max(a, c) < min(b, d):
                    shared = (max(a, c), min(b, d))
                    cross += float(
                        np.sum(self._signal(j, shared, sigma) * self._signal(k, shared, sigma))
                    )
        return abs(cross) / max(np.sqrt(energy[j] * energy[k]), 1e-300)

    def resolve(self, cluster: list[int], sigma: FloatArray) -> None:
        """The targets of ``cluster`` fitted jointly on their footprints (a pair's tensors
        overlap, and fitting each with the other taken out converges slowly and leaves
        ghosts of the misfit); then, while a member is one the joint fit does not need (an
        F-test of the 6 parameters it adds at ``significance``), the least needed one is
        dropped and its detections go to the nearest remaining member."""
        windows = _merged([w for k in cluster for w in self.footprints[k]])
        pieces = [self.cleaned(window, tuple(cluster)) for window in windows]
        members = list(cluster)
        # The pruning works on thinned passes (each trial is a joint fit); the members kept
        # are fitted on every sample last.
        full, pieces = pieces, [piece.thinned(SWEEP_SAMPLES) for piece in pieces]
        fits = fit_dipoles(pieces, self.geometry, sigma, [self.fits[k].position for k in members])
        while len(members) > 1:
            rss, dof = _rss(fits[0], len(members), len(pieces))
            j = min(range(len(members)), key=lambda i: _moment_chi2(fits[i]))  # the weakest
            rest = [f.position for i, f in enumerate(fits) if i != j]
            fewer = fit_dipoles(pieces, self.geometry, sigma, rest)
            gain = (_rss(fewer[0], len(rest), len(pieces))[0] - rss) / 6 / (rss / dof)
            if gain >= f_isf(self.settings.significance, 6, dof):
                break
            dropped = members.pop(j)
            fits = fewer
            where = self.fits[dropped].position
            heir = min(range(len(members)), key=lambda i: _distance(fits[i], where))
            self.passes[members[heir]] += self.passes[dropped]
            self.passes[dropped] = []
        fits = fit_dipoles(full, self.geometry, sigma, [f.position for f in fits])
        for k, fit in zip(members, fits, strict=True):
            self.fits[k] = fit
            self.groups[k] = members[0] if len(members) > 1 else -1

    def drop_empty(self) -> None:
        """Forget the targets :meth:`resolve` dropped (no detections left)."""
        keep = [k for k, detections in enumerate(self.passes) if detections]
        self.fits = [self.fits[k] for k in keep]
        self.passes = [self.passes[k] for k in keep]
        self.footprints = [self.footprints[k] for k in keep]
        self.groups = [self.groups[k] for k in keep]

    def predicted(self, own: tuple[int, ...]) -> FloatArray:
        """The tensors (N, 3, 3) T/m of every target not in ``own`` along the survey."""
        return self._tensors(self.survey.positions, self.survey.rotations, own)

    def cleaned(self, window: tuple[int, int], own: tuple[int, ...]) -> Pass:
        """The samples of ``window`` minus the tensors of every target not in ``own``."""
        piece = self.survey.piece(*window)
        others = self._tensors(piece.positions, piece.rotations, own)
        return Pass(piece.positions, piece.rotations, piece.tensors - others, piece.t_s)

    def _tensors(
        self, positions: FloatArray, rotations: FloatArray, own: tuple[int, ...]
    ) -> FloatArray:
        out = np.zeros((len(positions), 3, 3))
        for k, fit in enumerate(self.fits):
            if k not in own and self.passes[k]:
                out += array_tensor(positions, rotations, self.geometry, fit.position, fit.moment)
        return out


def _merged(windows: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Windows (start, stop) with the overlapping ones joined."""
    out: list[tuple[int, int]] = []
    for start, stop in sorted(windows):
        if out and start < out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], stop))
        else:
            out.append((start, stop))
    return out


def _distance(fit: DipoleFit, position: FloatArray) -> float:
    return float(np.linalg.norm(fit.position - position))


def _rss(fit: DipoleFit, count: int, n_passes: int) -> tuple[float, float]:
    """Whitened residual sum of squares of a (joint) fit of ``count`` dipoles, and its
    degrees of freedom."""
    dof = max(5 * fit.n_samples - 6 * count - 5 * n_passes, 1)
    return fit.chi2_reduced * dof, float(dof)


def footprint(
    survey: Survey,
    geometry: TetraGeometry,
    fit: DipoleFit,
    sigma: FloatArray,
    legs: list[tuple[int, int]],
    level: float,
) -> list[tuple[int, int]]:
    """The windows (start, stop), one per leg at most, where the target's predicted tensor
    exceeds ``level`` in noise units (root of the sum of its whitened five components
    squared): the passes that see it."""
    out = []
    for start, stop in legs:
        piece = survey.piece(start, stop)
        predicted = array_tensor(
            piece.positions, piece.rotations, geometry, fit.position, fit.moment
        )
        strength = np.sqrt(
            np.sum(
                (symmetric_components(to_world(predicted, piece.rotations)) / sigma) ** 2, axis=1
            )
        )
        seen = np.flatnonzero(strength > level)
        if len(seen) >= 10:
            out.append((start + int(seen[0]), start + int(seen[-1]) + 1))
    return out


def _nearest(fit: DipoleFit, fits: list[DipoleFit], settings: LocatorSettings) -> int | None:
    """The known target ``fit`` is one with (see the module docstring), or None."""
    best, best_distance = None, np.inf
    for k, other in enumerate(fits):
        spread = np.sqrt(np.trace(fit.covariance[:3, :3]) + np.trace(other.covariance[:3, :3]))
        limit = settings.associate_sigmas * min(spread, settings.associate_max_sigma_m)
        distance = float(np.linalg.norm(fit.position - other.position))
        if distance < limit + settings.associate_floor_m and distance < best_distance:
            best, best_distance = k, distance
    return best


def significant(fit: DipoleFit, probability: float) -> bool:
    """Whether the moment differs from zero at false-alarm ``probability`` (chi-square test
    of ``m^T C_m^-1 m`` with 3 degrees of freedom): a detection that a background alone
    explains (a blip of noise, a leg's end) is no target."""
    return _moment_chi2(fit) > chi2_isf(probability, 3)


def _moment_chi2(fit: DipoleFit) -> float:
    """``m^T C_m^-1 m`` of a fit's moment (0 when its covariance is singular)."""
    try:
        return float(fit.moment @ np.linalg.solve(fit.covariance[3:6, 3:6], fit.moment))
    except np.linalg.LinAlgError:
        return 0.0
