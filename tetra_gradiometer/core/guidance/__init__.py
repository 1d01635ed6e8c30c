"""Trim guidance: how well the samples collected so far would calibrate, and what to fly next.

:mod:`.statistics` reduces trim samples to what the known-gradient solve sees of them
(:class:`TrimStatistics`: a 4x4 Gram matrix, 4x9 cross products, a sum of squares, coverage
counts; O(1) memory, sums). :func:`assess` turns them into a :class:`TrimAssessment`:

* **sensor noise**: the fit's own estimate (its whitened residual, the number the solve puts
  in ``details['sensor_noise_nT']``) once ``MIN_SAMPLES`` are in; before, a configured value;
* **parameter covariance** ``sigma^2 (A^T A + sigma^2 P)^-1``: the fit's, plus a weak prior
  ``P`` (:data:`PRIOR_K`, :data:`PRIOR_B_T` per element, 1-sigma) that bounds the directions
  the data do not see (a pseudo-inverse would call them exact);
* **predicted compensated sigma**: :func:`~..uncertainty.compensated_sigma` with that
  covariance at a representative survey, level flight on the compass headings
  :data:`SURVEY_HEADINGS_DEG` with roll and pitch each of 0 and ±:data:`SURVEY_SWAY_DEG`
  (sea-state sway), in the site's Earth field; RMS over the 9 components and the attitudes.
  The **noise floor** is the RMS of :func:`~..uncertainty.noise_sigma` (sensor noise alone);
* **enough** when the predicted sigma is at most :data:`ENOUGH_RATIO` times the floor, with at
  least ``MIN_SAMPLES`` samples and an attitude-coverage condition number the solver accepts;
* **advice**: each candidate manoeuvre, turning through a :data:`SECTOR_DEG` heading sector in
  :data:`MANOEUVRE_DURATION_S` while rolling ±:data:`MANOEUVRE_AMPLITUDE_DEG`, pitching as
  much, or level, is flown in the simulator's pose model (:class:`~..simulator.TrimManoeuvre`)
  in the site's Earth field at the data rate; its body-frame fields are added to the Gram
  matrix, and the one that leaves the smallest *worst* predicted sigma over the survey
  attitudes is advised ("roll ±15° on heading 120–180°"). What a manoeuvre is worth is the
  new body-frame field directions it brings: on a trim pitched on one heading, rolling and
  turning to a heading with another field component across the vehicle both bring them, and
  the ranking says which brings more.

Headings are compass headings (degrees clockwise from north). SI units inside;
``TrimAssessment.to_dict`` and the texts give nT and nT/m.
"""

from .assessment import (
    ENOUGH_RATIO,
    MANOEUVRE_AMPLITUDE_DEG,
    MANOEUVRE_DURATION_S,
    PRIOR_B_T,
    PRIOR_K,
    SECTOR_DEG,
    SURVEY_HEADINGS_DEG,
    SURVEY_SWAY_DEG,
    Advice,
    TrimAssessment,
    assess,
    survey_attitudes,
)
from .statistics import (
    Coverage,
    TrimStatistics,
    attitude_rotation,
    coverage_condition,
    heading_roll_pitch,
    trim_statistics,
)

__all__ = [
    'ENOUGH_RATIO',
    'MANOEUVRE_AMPLITUDE_DEG',
    'MANOEUVRE_DURATION_S',
    'PRIOR_B_T',
    'PRIOR_K',
    'SECTOR_DEG',
    'SURVEY_HEADINGS_DEG',
    'SURVEY_SWAY_DEG',
    'Advice',
    'Coverage',
    'TrimAssessment',
    'TrimStatistics',
    'assess',
    'attitude_rotation',
    'coverage_condition',
    'heading_roll_pitch',
    'survey_attitudes',
    'trim_statistics',
]
