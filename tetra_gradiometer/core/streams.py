"""Stream health: each magnetometer stream checked before sets are formed, its faults named
with the sensor and the time span. The one place for these checks, offline (the bag readers,
chunk by chunk: :class:`StreamChecker`) and live (the tensor node, message by message:
:class:`~.live_streams.LiveStreamCheck`, on the same bounds).

A stream is ``stamps_ns`` (n,) int64 header stamps, ``fields`` (n, 3) tesla and, from a bag,
``log_ns`` (n,) the recorder's log times. What is checked, and what follows:

* **zero stamps** (a driver that does not fill ``header.stamp``): a sensor whose stamps are
  all 0 is refused; some zero stamps are dropped and counted.
* **another epoch or clock**: a sensor whose stamps never overlap the others' (GPS against
  Unix time, a time zone, time since boot) is refused, with the offset and what it looks
  like. With log times, a sensor's ``stamp - log time`` is compared with the other sensors'
  at the same log time (a recorder stall or a replay recorded faster moves all four alike):
  beyond :data:`CLOCK_TOLERANCE_S` on every message the sensor is refused, on some (a jump on
  one sensor only) those messages are dropped and counted, with their span.
* **duplicated stamps**: messages sharing a stamp with different readings are all dropped
  (which one is the sample is unknowable), identical repeats after the first too; over half
  of a sensor's messages in conflict is refused (its stamps are not sample times).
* **magnitude**: each sensor's median ``|B|`` against the Earth field (``earth_field_t``, the
  params' ``earth_field_enu``; else the range over the globe, :data:`EARTH_RANGE_T`) and
  against the other three sensors' median; beyond a factor :data:`MAGNITUDE_FACTOR` it is
  refused, naming the unit the factor matches (:data:`UNIT_FACTORS`: µT, Gauss, nT written
  as tesla ...) or saying none does.
* **coverage** (at the end, :meth:`StreamChecker.finish`): a sensor that starts late, stops
  early or falls silent for longer than ``max(OUTAGE_MIN_S, OUTAGE_PERIODS periods)``: the
  span without it and the sets lost (the span times the reference rate).

Why these bounds: the vehicle's own field at a sensor is at most twice the Earth's
(:data:`~.plausibility.MAX_B_T`), so a sensor's median ``|B|`` lies within 1/3 to 3 times the
Earth field; :data:`MAGNITUDE_FACTOR` 4 leaves a margin, and the unit factors are >= 1e3.
Header stamps and log times differ by the transport delay (ms; seconds when a recorder
stalls, and then on every sensor alike): :data:`CLOCK_TOLERANCE_S` 5 s.
Times in messages are seconds from the recording's first usable stamp.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import StreamError
from .types import FloatArray
from .units import NS_PER_S, S_PER_NS

__all__ = [
    'CLOCK_TOLERANCE_S',
    'EARTH_RANGE_T',
    'MAGNITUDE_FACTOR',
    'UNIT_FACTORS',
    'StreamChecker',
    'StreamFault',
    'StreamReport',
    'magnitude_mismatch',
]

#: Smallest and largest |B| of the Earth's main field over the globe (IGRF: ~22 µT in the
#: South Atlantic anomaly, ~67 µT near the south magnetic pole), tesla.
EARTH_RANGE_T = (2.2e-5, 6.7e-5)
#: A sensor's median |B| beyond this factor from the Earth field (or from the others'
#: median) is refused (see the module's docstring for why 4).
MAGNITUDE_FACTOR = 4.0
#: One sensor's median |B| beyond this factor from the other three's is refused: a sensor
#: beside a thruster may read three times the others, a unit mistake is >= 1e3.
SENSOR_FACTOR = 30.0
#: A sensor repeating its reading exactly this many times in a row is stuck (a fluxgate's
#: noise never repeats three components; 5 s at 10 Hz).
STUCK_READINGS = 50
#: Readings per sensor the magnitude test waits for (a few spikes move no median).
MAGNITUDE_SAMPLES = 20
#: ... and the most it keeps per sensor (the first readings of the recording).
MAGNITUDE_KEPT = 5000
#: Scale factors of |B| against the expected field and the mistake each one looks like:
#: a reading of 50 µT written as 50 (µT) is 1e6 times too large.
UNIT_FACTORS = (
    (1e9, 'nT written as tesla'),
    (1e7, 'milligauss written as tesla'),
    (1e6, 'µT written as tesla'),
    (1e4, 'Gauss written as tesla'),
    (1e3, 'mT written as tesla'),
    (1e-3, 'tesla divided by 1e3 once too often'),
    (1e-6, 'tesla divided by 1e6 once too often'),
    (1e-9, 'tesla divided by 1e9 once too often (converted to T twice)'),
)
#: A unit factor is named when the measured factor lies within half a decade of it.
UNIT_MATCH_DECADES = 0.5
#: Largest disagreement of a sensor's (stamp - log time) with the other sensors', s.
CLOCK_TOLERANCE_S = 5.0
#: A sensor silent longer than max(OUTAGE_MIN_S, OUTAGE_PERIODS of its periods) is named.
OUTAGE_MIN_S = 1.0
OUTAGE_PERIODS = 10.0
#: Offsets between clocks that have a name (seconds, what it looks like).
KNOWN_OFFSETS_S = (
    (315_964_800.0, 'GPS time against Unix time (epochs 1980-01-06 and 1970-01-01)'),
    (37.0, 'TAI against UTC (37 leap seconds)'),
    (18.0, 'GPS against UTC (18 leap seconds)'),
)

TOPICS = tuple(f'/tetra/mag{i + 1}' for i in range(4))


@dataclass(frozen=True)
class StreamFault:
    """One fault of one stream (or of all: ``sensor`` None) that was warned about and counted.

    Attributes
    ----------
    sensor : 0..3, or None for every sensor
    kind : 'zero_stamps', 'clock_jump', 'duplicate_stamps', 'starts_late', 'stops', 'gap'
    start_s, end_s : the span, s from the recording's first stamp
    messages : messages of the sensor dropped for it
    sets_lost : sets lost for it (estimated: the span times the reference rate)
    text : one line naming the sensor, the span and the loss
    """

    sensor: int | None
    kind: str
    start_s: float
    end_s: float
    messages: int
    sets_lost: int
    text: str

    def as_dict(self) -> dict[str, object]:
        return {
            'topic': 'all' if self.sensor is None else TOPICS[self.sensor],
            'kind': self.kind,
            'start_s': round(self.start_s, 3),
            'end_s': round(self.end_s, 3),
            'messages_dropped': self.messages,
            'sets_lost': self.sets_lost,
            'text': self.text,
        }


@dataclass
class StreamReport:
    """The faults of a read, in the order found; empty when the streams are healthy."""

    faults: list[StreamFault] = field(default_factory=list)

    @property
    def sets_lost(self) -> int:
        return sum(f.sets_lost for f in self.faults)

    def text(self) -> str:
        """'' or the faults' lines joined by '; ' (at most five, then how many more)."""
        lines = [f.text for f in self.faults[:5]]
        if len(self.faults) > 5:
            lines.append(f'{len(self.faults) - 5} more stream faults')
        return '; '.join(lines)

    def as_dict(self) -> dict[str, object]:
        """For output metadata (calibration diagnostics, reports)."""
        return {
            'stream_faults': [f.as_dict() for f in self.faults],
            'sets_lost_stream_faults': self.sets_lost,
        }


def _span_text(start_s: float, end_s: float) -> str:
    return f'{start_s:.1f}-{end_s:.1f} s'


def _name(sensor: int | None) -> str:
    return 'every magnetometer' if sensor is None else f'{TOPICS[sensor]} (sensor {sensor + 1})'


def magnitude_mismatch(ratio: float) -> str:
    """What a ratio |B| measured / |B| expected looks like: a unit mistake from
    :data:`UNIT_FACTORS` within half a decade, or 'no unit factor explains it'."""
    if not ratio > 0:
        return 'it reads 0 (a sensor not connected?)'
    decades = np.log10(ratio)
    for factor, mistake in UNIT_FACTORS:
        if abs(decades - np.log10(factor)) < UNIT_MATCH_DECADES:
            return f'it looks like {mistake}'
    return 'no unit factor (µT, Gauss, nT) explains it: a scale error?'


def _offset_text(offset_s: float) -> str:
    """'3600 s (1 h; a whole number of hours: a time zone?)' and the like."""
    size = abs(offset_s)
    parts = [f'{offset_s:+.6g} s']
    if size >= 86_400 * 365:
        parts.append(f'{size / (86_400 * 365.25):.1f} years')
    for known, what in KNOWN_OFFSETS_S:
        if abs(size - known) < 2.0:
            return f'{parts[0]} ({what}?)'
    if size >= 3_600 and abs(size / 3_600 - round(size / 3_600)) * 3_600 < 5.0 and size < 86_400:
        return f'{parts[0]} ({round(size / 3_600)} h: a time zone?)'
    return ' ('.join(parts) + (')' if len(parts) > 1 else '')


@dataclass
class _Coverage:
    """One sensor's coverage so far: first and last stamp, period, silences, drops."""

    first: int | None = None
    last: int | None = None
    period_ns: float | None = None
    gaps: list[tuple[int, int]] = field(default_factory=list)
    count: int = 0

    def add(self, stamps: np.ndarray, outage_ns: float | None) -> None:
        if not len(stamps):
            return
        stamps = np.sort(stamps)
        joined = stamps if self.last is None else np.concatenate([[self.last], stamps])
        intervals = np.diff(joined)
        if self.period_ns is None and len(intervals) >= 2:
            self.period_ns = float(np.median(intervals[intervals > 0]))
        limit = outage_ns if outage_ns is not None else self.outage_ns()
        for i in np.flatnonzero(intervals > limit):
            self.gaps.append((int(joined[i]), int(joined[i + 1])))
        self.first = int(stamps[0]) if self.first is None else self.first
        self.last = int(stamps[-1]) if self.last is None else max(self.last, int(stamps[-1]))
        self.count += len(stamps)

    def outage_ns(self) -> float:
        period = self.period_ns or 0.0
        return max(OUTAGE_MIN_S * NS_PER_S, OUTAGE_PERIODS * period)


class StreamChecker:
    """The offline checks of the four streams, fed chunk by chunk (see the module docstring).

    Parameters
    ----------
    earth_field_t : expected |B| of the Earth field, tesla (the params' ``earth_field_enu``),
        or None: the range over the globe and the other sensors
    source : what the messages name first (the bag's path)
    reference_rate_hz : the rate of the reference instants (0: sensor 1's own rate), Hz,
        for the sets lost in a span
    """

    def __init__(
        self,
        earth_field_t: float | None = None,
        source: str = '',
        reference_rate_hz: float = 0.0,
    ) -> None:
        self.earth_field_t = earth_field_t
        self.source = f'{source}: ' if source else ''
        self.reference_rate_hz = float(reference_rate_hz)
        self.report = StreamReport()
        self.origin_ns: int | None = None
        self._coverage = [_Coverage() for _ in range(4)]
        self._dropped: dict[tuple[int, str], list] = {}  # (sensor, kind) -> [n, first, last]
        self._jumps: dict[int, float] = {}  # sensor -> its stamps' jump, s
        self._norms: list[list[float]] = [[] for _ in range(4)]  # the first readings' |B|
        self._norm_stamps: list[list[int]] = [[] for _ in range(4)]
        self._magnitudes_checked = False
        self._conflicts = [[0, 0] for _ in range(4)]  # messages in conflict, messages seen

    # ----------------------------------------------------------------- per chunk

    def check(
        self,
        stamps: list[np.ndarray],
        fields: list[FloatArray],
        log_ns: list[np.ndarray] | None = None,
        final: bool = False,
    ) -> tuple[list[np.ndarray], list[FloatArray]]:
        """Check one chunk of the four streams; return them without the dropped messages.
        ``final``: the last chunk (the magnitude test decides on what it has).

        Raises
        ------
        StreamError
            A stream that cannot be used (all stamps zero, another epoch, a unit factor,
            stamps that are not sample times).
        """
        logs = log_ns if log_ns is not None else [np.asarray(s) for s in stamps]
        keep = [np.ones(len(s), bool) for s in stamps]
        self._zero_stamps(stamps, logs, keep)
        self._duplicates(stamps, fields, logs, keep)
        self._stuck(stamps, fields, keep)
        if log_ns is not None:
            self._clock_jumps(stamps, log_ns, keep)
        stamps = [s[k] for s, k in zip(stamps, keep, strict=True)]
        fields = [f[k] for f, k in zip(fields, keep, strict=True)]
        self._epochs(stamps)
        if self.origin_ns is None and any(len(s) for s in stamps):
            self.origin_ns = min(int(s.min()) for s in stamps if len(s))
        self._magnitudes(stamps, fields, final)
        for sensor, sensor_stamps in enumerate(stamps):
            self._coverage[sensor].add(sensor_stamps, None)
        return stamps, fields

    def _seconds(self, stamp_ns: float) -> float:
        return (stamp_ns - (self.origin_ns or 0)) * S_PER_NS

    def _drop(self, sensor: int, kind: str, stamps_ns: np.ndarray) -> None:
        """Count dropped messages of ``kind`` with their span (stamps on the common clock)."""
        if not len(stamps_ns):
            return
        entry = self._dropped.setdefault((sensor, kind), [0, np.inf, -np.inf])
        entry[0] += len(stamps_ns)
        entry[1] = min(entry[1], float(np.min(stamps_ns)))
        entry[2] = max(entry[2], float(np.max(stamps_ns)))

    def _zero_stamps(
        self, stamps: list[np.ndarray], logs: list[np.ndarray], keep: list[np.ndarray]
    ) -> None:
        # A stamp 0 in a recording whose other stamps lie near the epoch is a sample time.
        near = [bool(np.any(np.abs(s[s != 0]) < CLOCK_TOLERANCE_S * NS_PER_S)) for s in stamps]
        zero = [(s == 0) & (not n) for s, n in zip(stamps, near, strict=True)]
        full = [len(s) > 1 and bool(z.all()) for s, z in zip(stamps, zero, strict=True)]
        if all(full):
            raise StreamError(
                f'{self.source}every header stamp of {", ".join(TOPICS)} is 0 (a driver that '
                'does not fill header.stamp): sets cannot be formed without sample times'
            )
        for sensor, is_full in enumerate(full):
            if is_full:
                raise StreamError(
                    f'{self.source}every header stamp of {_name(sensor)} is 0 (a driver that '
                    f'does not fill header.stamp; {len(stamps[sensor])} messages): its '
                    'readings cannot be placed in time'
                )
        for sensor, z in enumerate(zero):
            keep[sensor] &= ~z
            self._drop(sensor, 'zero_stamps', logs[sensor][z])

    def _duplicates(
        self,
        stamps: list[np.ndarray],
        fields: list[FloatArray],
        logs: list[np.ndarray],
        keep: list[np.ndarray],
    ) -> None:
        for sensor, (s, f) in enumerate(zip(stamps, fields, strict=True)):
            candidates = np.flatnonzero(keep[sensor])
            if len(candidates) < 2:
                continue
            order = candidates[np.argsort(s[candidates], kind='stable')]
            same = s[order][1:] == s[order][:-1]
            if not same.any():
                continue
            group = np.concatenate([[0], np.cumsum(~same)])
            differs = same & np.any(f[order][1:] != f[order][:-1], axis=1)
            conflicting = np.isin(group, group[1:][differs])
            repeated = np.concatenate([[False], same]) & ~conflicting
            n_conflict = int(conflicting.sum())
            self._conflicts[sensor][0] += n_conflict
            self._conflicts[sensor][1] += len(candidates)
            n_conflict, n_seen = self._conflicts[sensor]
            if n_seen >= MAGNITUDE_SAMPLES and n_conflict > 0.5 * n_seen:
                raise StreamError(
                    f'{self.source}{_name(sensor)}: {n_conflict} of {n_seen} messages '
                    'share their header stamp with a different reading: its stamps are not '
                    'sample times'
                )
            keep[sensor][order[conflicting | repeated]] = False
            self._drop(sensor, 'duplicate_stamps', s[order[conflicting]])

    def _stuck(
        self, stamps: list[np.ndarray], fields: list[FloatArray], keep: list[np.ndarray]
    ) -> None:
        """Runs of :data:`STUCK_READINGS` or more readings equal to the one before, on some
        sensors but not all (all four repeating is a vehicle at rest read coarsely): the
        repeats are dropped (the first of a run was a reading)."""
        runs: dict[int, list[np.ndarray]] = {}
        for sensor, (s, f) in enumerate(zip(stamps, fields, strict=True)):
            index = np.flatnonzero(keep[sensor])
            order = index[np.argsort(s[index], kind='stable')]
            same = np.all(f[order][1:] == f[order][:-1], axis=1)
            edges = np.flatnonzero(np.diff(np.concatenate([[0], same.astype(int), [0]])))
            starts, ends = edges[::2], edges[1::2]
            runs[sensor] = [
                order[a + 1 : b + 1]
                for a, b in zip(starts, ends, strict=True)
                if b - a >= STUCK_READINGS - 1
            ]
        if all(runs.values()):
            return
        for sensor, repeats in runs.items():
            for index in repeats:
                keep[sensor][index] = False
                self._drop(sensor, 'stuck', stamps[sensor][index])

    def _clock_jumps(
        self, stamps: list[np.ndarray], logs: list[np.ndarray], keep: list[np.ndarray]
    ) -> None:
        """Each message's (stamp - log) against the other sensors' at its log time."""
        offsets = []
        known = [log[k] for log, k in zip(logs, keep, strict=True) if k.any()]
        base = min((int(log.min()) for log in known), default=0)
        for s, log, k in zip(stamps, logs, keep, strict=True):
            order = np.argsort(log[k], kind='stable')
            # Relative to the earliest log time: float64 resolves ns only below ~1e15 ns.
            relative = (log[k][order] - base).astype(float)
            offsets.append((relative, (s[k] - log[k])[order].astype(float)))
        for sensor in range(4):
            others = [o for j, o in enumerate(offsets) if j != sensor and len(o[0])]
            log, own = offsets[sensor]
            if not others or not len(log):
                continue
            reference = np.median([np.interp(log, lo, off) for lo, off in others], axis=0)
            off = np.abs(own - reference) > CLOCK_TOLERANCE_S * NS_PER_S
            if not off.any():
                continue
            shift = float(np.median(own[off] - reference[off])) * S_PER_NS
            if off.all():
                raise StreamError(
                    f'{self.source}{_name(sensor)}: its header stamps are '
                    f"{_offset_text(shift)} off the other sensors' (against the log times of "
                    'the bag): another epoch or clock; its readings cannot be matched'
                )
            index = np.flatnonzero(keep[sensor])[np.argsort(logs[sensor][keep[sensor]])][off]
            keep[sensor][index] = False
            # Their span on the common clock: the log time plus the others' offset.
            self._drop(sensor, 'clock_jump', (log[off] + reference[off]).astype(np.int64) + base)
            self._jumps[sensor] = shift

    def _epochs(self, stamps: list[np.ndarray]) -> None:
        """A sensor whose stamps never overlap the others': another epoch or clock."""
        ranges = [(int(s.min()), int(s.max())) if len(s) else None for s in stamps]
        present = [i for i, r in enumerate(ranges) if r is not None]
        if len(present) < 2:
            return
        medians = {i: float(np.median(stamps[i])) for i in present}
        for sensor in present:
            others = [ranges[j] for j in present if j != sensor]
            lo, hi = min(r[0] for r in others), max(r[1] for r in others)  # type: ignore[index]
            first, last = ranges[sensor]  # type: ignore[misc]
            if max(lo - last, first - hi) <= CLOCK_TOLERANCE_S * NS_PER_S:
                continue  # overlapping, or apart by less than a recorder's delay (chunk edges)
            reference = float(np.median([medians[j] for j in present if j != sensor]))
            shift = (medians[sensor] - reference) * S_PER_NS
            raise StreamError(
                f'{self.source}{_name(sensor)}: its stamps lie {_offset_text(shift)} from the '
                "other sensors' and never overlap them: another epoch or clock"
            )

    def _magnitudes(
        self, stamps: list[np.ndarray], fields: list[FloatArray], final: bool = False
    ) -> None:
        """Each sensor's median |B| against the Earth field, then against the other three."""
        if self._magnitudes_checked:
            return
        for sensor, f in enumerate(fields):
            norms = np.linalg.norm(f, axis=1)
            room = MAGNITUDE_KEPT - len(self._norms[sensor])
            finite = np.isfinite(norms)
            self._norms[sensor].extend(norms[finite][:room].tolist())
            self._norm_stamps[sensor].extend(stamps[sensor][finite][:room].tolist())
        if any(len(n) < MAGNITUDE_SAMPLES for n in self._norms) and not final:
            return  # too few readings yet to tell a unit from a spike
        self._magnitudes_checked = True
        for sensor, sensor_stamps in enumerate(stamps):
            if len(sensor_stamps) and not self._norms[sensor]:
                span = _span_text(
                    self._seconds(sensor_stamps[0]), self._seconds(sensor_stamps[-1])
                )
                raise StreamError(
                    f'{self.source}{_name(sensor)}: every reading is NaN or inf ({span})'
                )
        stamps = [np.asarray(s, np.int64) for s in self._norm_stamps]
        medians = {s: float(np.median(n)) for s, n in enumerate(self._norms) if n}
        if self.earth_field_t:
            lo = hi = self.earth_field_t
            what = f'the Earth field of {lo * 1e6:.3g} µT (earth_field_enu)'
        else:
            lo, hi = EARTH_RANGE_T
            what = (
                f'a {np.sqrt(lo * hi) * 1e6:.0f} µT Earth field '
                f"(the globe's {lo * 1e6:.0f}-{hi * 1e6:.0f} µT)"
            )
        # The factor is named against the expected value (the range's geometric middle).
        off = {
            s: m / np.sqrt(lo * hi)
            for s, m in medians.items()
            if not lo / MAGNITUDE_FACTOR <= m <= hi * MAGNITUDE_FACTOR
        }
        if off:
            self._refuse_magnitude(stamps, medians, off, what)
        if len(medians) < 3:
            return
        for sensor, m in medians.items():  # one sensor against the other sensors
            others = float(np.median([v for s, v in medians.items() if s != sensor]))
            ratio = m / others if others > 0 else np.inf
            if others > 0 and not 1 / SENSOR_FACTOR <= ratio <= SENSOR_FACTOR:
                what = f"the other sensors' median {others * 1e6:.3g} µT"
                self._refuse_magnitude(stamps, medians, {sensor: ratio}, what)

    def _refuse_magnitude(
        self,
        stamps: list[np.ndarray],
        medians: dict[int, float],
        off: dict[int, float],
        what: str,
    ) -> None:
        sensor: int | None = None if len(off) == len(medians) == 4 else min(off)
        ratio = float(np.median(list(off.values()))) if sensor is None else off[sensor]
        chosen = [s for s in off] if sensor is None else [sensor]
        first = min(int(stamps[s].min()) for s in chosen)
        last = max(int(stamps[s].max()) for s in chosen)
        magnitude = float(np.median([medians[s] for s in chosen]))
        raise StreamError(
            f'{self.source}{_name(sensor)} reads a median |B| of {magnitude:.4g} '
            f'({_span_text(self._seconds(first), self._seconds(last))}), {ratio:.3g}x {what}: '
            f'{magnitude_mismatch(ratio)} (the data contract is tesla)'
        )

    # ----------------------------------------------------------------- at the end

    def finish(self) -> StreamReport:
        """The warned faults of the whole read: drops and coverage, with spans and sets lost."""
        cover = [(c.first, c.last) for c in self._coverage if c.first is not None]
        if self.origin_ns is None or not cover:
            return self.report
        start, end = min(c[0] for c in cover), max(c[1] for c in cover if c[1] is not None)
        for (sensor, kind), (n, lo, hi) in sorted(self._dropped.items()):
            span = (self._seconds(lo), self._seconds(hi))
            jump = _offset_text(self._jumps.get(sensor, 0.0))
            what = {
                'zero_stamps': f'{n} messages with header stamp 0 dropped (log times',
                'duplicate_stamps': f'{n} messages sharing a stamp with another reading dropped (',
                'clock_jump': f'{n} messages whose stamps jumped {jump} on it alone dropped (',
                'stuck': f'{n} readings repeating the one before exactly (stuck) dropped (',
            }[kind]
            # The sets lost are counted once, by the coverage faults below.
            text = f'{_name(sensor)}: {what}{_span_text(*span)})'
            self.report.faults.append(StreamFault(sensor, kind, *span, n, 0, text))
        for sensor, coverage in enumerate(self._coverage):
            self._coverage_faults(sensor, coverage, start, end)
        return self.report

    def _coverage_faults(self, sensor: int, coverage: _Coverage, start: int, end: int) -> None:
        """A late start, silences and an early stop of one sensor, each with its sets lost."""
        if coverage.first is None or coverage.last is None:
            return
        period = self._coverage[0].period_ns
        rate = self.reference_rate_hz or (NS_PER_S / period if period else 0.0)
        limit = coverage.outage_ns()
        total_s = (end - start) * S_PER_NS
        spans = [('gap', a, b, 'falls silent') for a, b in coverage.gaps]
        if coverage.first - start > limit:
            at = self._seconds(coverage.first)
            spans.insert(0, ('starts_late', start, coverage.first, f'starts late, at {at:.1f} s'))
        if end - coverage.last > limit:
            at = self._seconds(coverage.last)
            spans.append(('stops', coverage.last, end, f'stops at {at:.1f} s of {total_s:.1f} s'))
        for kind, a, b, verb in spans:
            lost = int(round((b - a) * S_PER_NS * rate))
            text = (
                f'{_name(sensor)} {verb}: no data {_span_text(self._seconds(a), self._seconds(b))}'
            )
            fault = StreamFault(
                sensor,
                kind,
                self._seconds(a),
                self._seconds(b),
                0,
                lost,
                f'{text}, {lost} sets lost',
            )
            self.report.faults.append(fault)
