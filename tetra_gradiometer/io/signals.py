"""A declared signal's values from a bag: one field of any message the bag records
(:mod:`tetra_gradiometer.core.effects.recorded_signal` says how one is declared).

rosbags decodes a message of any type whose definition the typestore or the bag carries
(mcap and rosbag2 sqlite3 bags store them), so no type is named in code. A message with a
header is placed by its stamp, one without (``std_msgs/Float64``, as power boards publish)
by its log time. A message whose field cannot be read (a joint missing from this message)
is skipped and counted like an undecodable one. The ``data`` of a ``std_msgs`` number
(Float64, Float32) is read straight from its CDR: rosbags' deserializer per message took
most of the time of reading a 30-minute mission's power-board topics.
"""

from __future__ import annotations

import math
import struct
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import BagError
from .bag_decode import _CDR_BE, _CDR_LE, checked_stamp_ns
from .bag_skips import SkippedMessage, guarded_messages

if TYPE_CHECKING:  # only an annotation: the nodes import this module without rosbags
    from .bag import MagneticBag, Series

__all__ = ['field_value', 'read_signal']

#: Messages that are one number, ``data``, with no header: its struct code.
PLAIN_NUMBERS = {'std_msgs/msg/Float64': 'd', 'std_msgs/msg/Float32': 'f'}


def _plain_number(raw: bytes, code: str) -> float:
    """The ``data`` of a plain number's CDR (right after the 4-byte encapsulation, which
    aligns it), or ValueError naming why not."""
    kind = bytes(raw[:2])
    if kind not in (_CDR_LE, _CDR_BE) or len(raw) < 4 + struct.calcsize(code):
        raise ValueError('not a plain CDR number')
    number = float(struct.unpack_from(('<' if kind == _CDR_LE else '>') + code, raw, 4)[0])
    if not math.isfinite(number):
        raise ValueError(f'data is {number}')
    return number


def field_value(msg: Any, path: str) -> float:
    """The number at ``path`` in ``msg``: attribute names joined by dots, an element by
    ``[index]`` or, in an array beside a ``name`` array (JointState), by ``[name]``.

    Raises
    ------
    ValueError
        Naming what is missing (a field, a joint, an index) or not a number.
    """
    value = msg
    for part in path.split('.'):
        attribute, _, key = part.partition('[')
        parent = value
        if not hasattr(value, attribute):
            fields = [f for f in dir(value) if not f.startswith('_')]
            raise ValueError(f'no field {attribute!r} (it has: {", ".join(fields)})')
        value = getattr(value, attribute)
        if key:
            key = key[:-1]
            if key.lstrip('-').isdigit():
                if not -len(value) <= int(key) < len(value):
                    raise ValueError(f'{attribute}[{key}]: it has {len(value)} elements')
                value = value[int(key)]
            else:
                names = [str(n) for n in getattr(parent, 'name', ())]
                if key not in names:
                    raise ValueError(f'no {key!r} in name (it has: {", ".join(names)})')
                value = value[names.index(key)]
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f'{path} is {number}')
    return number


def read_signal(bag: MagneticBag, topic: str, path: str) -> Series | None:
    """The values (n, 1) of ``path`` in ``topic``'s messages by stamp (a header's, else the
    log time); None when the bag does not record ``topic``.

    Raises
    ------
    BagError
        The field cannot be read in more than the bag's ``max_skipped_fraction`` of the
        messages (named with the first reason: the fields or joints the message has).
    """
    from .bag import Series

    # The name as recorded too: a bag's one Temperature topic also stands for the contract's
    # temperature (io/bag.py), and a signal declared on it is still its own.
    connections = [c for c in bag.reader.connections if topic in (c.topic, bag.topic_of(c.topic))]
    if not connections:
        return None
    stamps, values, lost, first = [], [], 0, ''

    def on_skip(record: SkippedMessage) -> None:
        nonlocal lost
        lost += bag.record_skip(record)

    for connection, log_ns, raw in guarded_messages(bag.reader, connections, on_skip):
        try:
            code = PLAIN_NUMBERS.get(connection.msgtype) if path == 'data' else None
            if code is not None:
                value, stamp = _plain_number(raw, code), int(log_ns)
            else:
                msg: Any = bag.reader.deserialize(raw, connection.msgtype)
                value = field_value(msg, path)
                header = getattr(msg, 'header', None)
                stamp = checked_stamp_ns(header.stamp) if header is not None else int(log_ns)
        except Exception as error:  # any message type: a field it lacks, a damaged payload
            first = first or f'{connection.msgtype}: {error}'
            on_skip(SkippedMessage(topic, log_ns, f'{path}: {error}'[:200]))
            continue
        stamps.append(stamp)
        values.append(value)
    total = sum(c.msgcount for c in connections)
    if total and lost > bag.max_skipped_fraction * total:
        raise BagError(
            f'{bag.path}: {topic}#{path}: not read in {lost} of {total} messages: {first}'
        )
    if not stamps:
        return None
    order = np.argsort(stamps, kind='stable')
    return Series(
        np.asarray(stamps, dtype=np.int64)[order], np.asarray(values, dtype=float)[order, None]
    )
