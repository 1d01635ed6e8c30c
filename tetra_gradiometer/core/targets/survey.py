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
from scipy import stats

from ...errors import InputError
from ..geometry import TetraGeometry, to_world
from ..types import FloatArray
from .detection import Detection, DetectionResult, DetectorSettings, detect
from .forward import array_tensor, symmetric_components
from .localization import DipoleFit, Pass, fit_dipole

#: Refits of every target after the last one is found (each moves the footprints).
FINAL_SWEEPS = 2
#: While targets are being found, their fits take at most this many samples per pass.
SWEEP_SAMPLES = 300


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
    detection sample) and whether it is ``dipolar``."""

    fit: DipoleFit
    detections: list[Detection]
    first_seen_s: float
    last_seen_s: float
    dipolar: bool


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
        fit = fit_dipole([catalogue.cleaned(window, -1)], geometry, sigma)
        if not significant(fit, settings.significance):
            continue
        k = catalogue.add(fit, detection)
        catalogue.sweep(sigma, [k], thin=True)  # its footprint, then who shares it
        catalogue.sweep(sigma, catalogue.neighbours(k), thin=True)
        residual = survey.tensors - catalogue.predicted(-1)
        found = detect(survey.t_s, residual, survey.positions, survey.rotations, settings.detector)
        sigma = found.sigma  # with the targets out, more of the survey is quiet
    for _ in range(FINAL_SWEEPS):
        catalogue.sweep(sigma)
    fits, passes = catalogue.fits, catalogue.passes
    targets = []
    for fit, detections in zip(fits, passes, strict=True):
        dipolar = (
            fit.misfit_fraction <= settings.max_misfit or fit.chi2_reduced <= settings.max_chi2
        )
        targets.append(
            Target(
                fit,
                detections,
                float(min(survey.t_s[d.start] for d in detections)),
                float(max(survey.t_s[d.stop - 1] for d in detections)),
                bool(dipolar),
            )
        )
    targets.sort(key=lambda target: target.first_seen_s)
    return targets, first


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

    def add(self, fit: DipoleFit, detection: Detection) -> int:
        """A new target, or a new pass of the known target ``fit`` puts it at: its index."""
        k = _nearest(fit, self.fits, self.settings)
        if k is None:
            self.fits.append(fit)
            self.passes.append([])
            self.footprints.append([])
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
            pieces = [self.cleaned(window, k) for window in self.footprints[k]]
            if thin:
                pieces = [piece.thinned(SWEEP_SAMPLES) for piece in pieces]
            self.fits[k] = fit_dipole(pieces, self.geometry, sigma, fit.position)

    def predicted(self, own: int) -> FloatArray:
        """The tensors (N, 3, 3) T/m of every target but ``own`` along the survey."""
        return self._tensors(self.survey.positions, self.survey.rotations, own)

    def cleaned(self, window: tuple[int, int], own: int) -> Pass:
        """The samples of ``window`` minus the tensors of every target but ``own``."""
        piece = self.survey.piece(*window)
        others = self._tensors(piece.positions, piece.rotations, own)
        return Pass(piece.positions, piece.rotations, piece.tensors - others, piece.t_s)

    def _tensors(self, positions: FloatArray, rotations: FloatArray, own: int) -> FloatArray:
        out = np.zeros((len(positions), 3, 3))
        for k, fit in enumerate(self.fits):
            if k != own:
                out += array_tensor(positions, rotations, self.geometry, fit.position, fit.moment)
        return out


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
    covariance = fit.covariance[3:6, 3:6]
    try:
        value = float(fit.moment @ np.linalg.solve(covariance, fit.moment))
    except np.linalg.LinAlgError:
        return False
    return value > stats.chi2.isf(probability, 3)
