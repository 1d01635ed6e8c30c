"""The target node's outputs: one ``locate`` result as arrays and the ``targets.json``
record (:func:`located_targets`), and those as messages (:func:`pose_array_msg`,
:func:`target_markers_msg`). Beside ``conversions.py`` (its message classes, ``header``,
``pose_msg``), which is at the size limit of a module.

Choices: a target's pose has the moment's direction as its orientation, the rotation taking
+x onto the moment (:func:`x_axis_onto`; RViz draws a pose as an arrow along its x axis); a
detection's pose is the vehicle's (position and attitude of the track at the detection's
peak sample). A target's marker is a sphere whose axes are its 3-sigma position interval
along the odom axes (``6 sigma`` wide, at least :data:`MIN_MARKER_M`), labelled with the
moment's magnitude. Nothing non-finite is published: a target whose fit has a non-finite
value is left out and counted.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.targets import DetectionResult, Target
from ..core.types import FloatArray
from ..core.units import S_PER_NS
from ..io import conversions as cv
from ..io.targets import dumps, targets_document
from .track import TrackSnapshot

#: Marker spheres are at least this wide, m (a 5 mm sigma would be invisible).
MIN_MARKER_M = 0.1
#: Sphere and label colours (r, g, b, alpha), and the labels' height, m.
SPHERE_RGBA = (1.0, 0.5, 0.0, 0.5)
TEXT_RGBA = (1.0, 1.0, 1.0, 1.0)
TEXT_HEIGHT_M = 1.0
#: The markers' namespace (RViz groups and deletes by it).
MARKER_NAMESPACE = 'targets'
IDENTITY_XYZW = np.array([0.0, 0.0, 0.0, 1.0])


@dataclass(frozen=True)
class LocatedTargets:
    """One ``locate`` result as published.

    Attributes
    ----------
    stamp_ns : the stamp of the track's last sample, integer ns (the messages' header)
    positions, position_sigmas : (n, 3) m, odom frame, and their 1-sigma
    moments : (n, 3) A m^2, odom frame
    detection_positions : (k, 3) m, the track at each detection's peak
    detection_orientations : (k, 4) x, y, z, w, the vehicle's attitude there
    document : the ``targets.json`` text (io/targets.py)
    samples : samples searched
    dropped_non_finite : targets left out (a non-finite value in their fit)
    """

    stamp_ns: int
    positions: FloatArray
    position_sigmas: FloatArray
    moments: FloatArray
    detection_positions: FloatArray
    detection_orientations: FloatArray
    document: str
    samples: int
    dropped_non_finite: int


def _finite(target: Target) -> bool:
    fit = target.fit
    values = (fit.position, fit.position_sigma, fit.moment, fit.moment_sigma)
    scalars = (fit.rms, fit.chi2_reduced, target.first_seen_s, target.last_seen_s)
    return bool(all(np.all(np.isfinite(v)) for v in values) and np.all(np.isfinite(scalars)))


def located_targets(
    track: TrackSnapshot,
    targets: Sequence[Target],
    detected: DetectionResult,
    *,
    false_alarms_per_hour: float,
) -> LocatedTargets:
    """What the target node publishes for ``locate(track.survey, ...)``'s ``targets`` and
    first ``detected`` result (the JSON's times count from the track's first sample)."""
    kept = [target for target in targets if _finite(target)]
    peaks = np.array([d.peak for d in detected.detections], dtype=np.int64)
    document = targets_document(
        kept,
        tensor='compensated',
        t0_stamp_s=track.t0_ns * S_PER_NS,
        false_alarms_per_hour=false_alarms_per_hour,
        detections=len(peaks),
    )

    def column(values: list[FloatArray]) -> FloatArray:
        return np.array(values, dtype=float).reshape(-1, 3)

    return LocatedTargets(
        stamp_ns=track.last_ns,
        positions=column([t.fit.position for t in kept]),
        position_sigmas=column([t.fit.position_sigma for t in kept]),
        moments=column([t.fit.moment for t in kept]),
        detection_positions=track.survey.positions[peaks].reshape(-1, 3),
        detection_orientations=track.orientation_xyzw[peaks].reshape(-1, 4),
        document=dumps(document),
        samples=len(track.survey.t_s),
        dropped_non_finite=len(targets) - len(kept),
    )


def x_axis_onto(directions: FloatArray) -> FloatArray:
    """Quaternions (n, 4) x, y, z, w of the shortest rotations taking +x onto each of
    ``directions`` (n, 3) (of any length; a zero vector gives the identity)."""
    u = np.asarray(directions, dtype=float).reshape(-1, 3)
    length = np.linalg.norm(u, axis=1, keepdims=True)
    u = np.where(length > 0, u / np.where(length > 0, length, 1.0), [1.0, 0.0, 0.0])
    # [x cross u, 1 + x . u], normalized: half the angle between x and u about their normal.
    q = np.column_stack([np.zeros(len(u)), -u[:, 2], u[:, 1], 1.0 + u[:, 0]])
    q[np.linalg.norm(q, axis=1) < 1e-9] = [0.0, 0.0, 1.0, 0.0]  # onto -x: half a turn about z
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def pose_array_msg(
    types: cv.MessageTypes,
    positions: FloatArray,
    orientations_xyzw: FloatArray,
    stamp_ns: int,
    frame_id: str = cv.ODOM_FRAME,
) -> Any:
    """``geometry_msgs/PoseArray``: a pose per row of ``positions`` (n, 3) m and
    ``orientations_xyzw`` (n, 4)."""
    rows = zip(np.reshape(positions, (-1, 3)), np.reshape(orientations_xyzw, (-1, 4)), strict=True)
    return types[cv.POSE_ARRAY](
        header=cv.header(types, stamp_ns, frame_id),
        poses=[cv.pose_msg(types, p, q) for p, q in rows],
    )


def target_markers_msg(
    types: cv.MessageTypes,
    positions: FloatArray,
    position_sigmas: FloatArray,
    moments: FloatArray,
    stamp_ns: int,
    frame_id: str = cv.ODOM_FRAME,
) -> Any:
    """``visualization_msgs/MarkerArray`` of targets at ``positions`` (n, 3) m with
    ``position_sigmas`` (n, 3) m and ``moments`` (n, 3) A m^2: a DELETEALL first (the
    markers of an older result vanish), then per target ``k`` a sphere (id ``2k``) whose
    axes are ``6 sigma`` (at least :data:`MIN_MARKER_M`) and a label (id ``2k + 1``)
    :data:`TEXT_HEIGHT_M` above it, ``T<k+1> <|moment|> A m^2``. rclpy's message types (the
    rosbags ones would need every field given)."""
    marker, head = types[cv.MARKER], cv.header(types, stamp_ns, frame_id)
    out = [marker(header=head, ns=MARKER_NAMESPACE, action=marker.DELETEALL)]
    diameters = np.maximum(6.0 * np.reshape(position_sigmas, (-1, 3)), MIN_MARKER_M)
    for k, (p, d, m) in enumerate(zip(positions, diameters, moments, strict=True)):
        label = f'T{k + 1} {np.linalg.norm(m):.3g} A m^2'
        above = np.asarray(p, dtype=float) + [0.0, 0.0, d[2] / 2 + TEXT_HEIGHT_M]
        for i, kind, at, scale, color, text in (
            (2 * k, marker.SPHERE, p, d, SPHERE_RGBA, ''),
            (2 * k + 1, marker.TEXT_VIEW_FACING, above, (0, 0, TEXT_HEIGHT_M), TEXT_RGBA, label),
        ):
            out.append(
                marker(
                    header=head,
                    ns=MARKER_NAMESPACE,
                    id=i,
                    type=kind,
                    action=marker.ADD,
                    pose=cv.pose_msg(types, at, IDENTITY_XYZW),
                    scale=_vector3(types, scale),
                    color=types[cv.COLOR_RGBA](**dict(zip('rgba', color, strict=True))),
                    text=text,
                )
            )
    return types[cv.MARKER_ARRAY](markers=out)


def _vector3(types: cv.MessageTypes, values: Sequence[float]) -> Any:
    x, y, z = (float(v) for v in values)
    return types['geometry_msgs/msg/Vector3'](x=x, y=y, z=z)
