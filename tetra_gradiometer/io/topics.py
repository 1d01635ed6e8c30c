"""Which recorded topics a bag is read as: the contract's names (``conversions.
CONTRACT_TOPICS``), a vehicle namespace in front of them, or names the user gives.

:class:`BagSource` is a bag folder with the names a command was given for it (``--namespace``,
``--mag-topics``, ``--odom-topic``); it is a path-like, so the pipelines pass it where they
pass a path and :class:`~.bag.MagneticBag` reads it with those names. Every name given must
be a topic the bag records (an error naming what it has); with none given, a contract topic
the bag records only under one other namespace is read from there (:func:`namespaced`), with
a line saying so.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

from ..errors import BagError, InputError
from . import conversions as cv

__all__ = ['BagSource', 'checked_remap', 'namespaced', 'topic_list']

#: The message types each of ``conversions.CONTRACT_TOPICS`` may hold (the tensor: a
#: GradientTensor, or the JointState of older recordings).
CONTRACT_TYPES = (
    *((cv.MAGNETIC_FIELD,),) * 4,
    (cv.GRADIENT_TENSOR, cv.JOINT_STATE),
    (cv.ODOMETRY,),
    (cv.TEMPERATURE,),
    (cv.BATTERY_STATE,),
)


def topic_list(text: str, count: int | None = None, what: str = 'topics') -> tuple[str, ...]:
    """Absolute ROS topic names from ``/a,/b``; ``count`` of them when given.

    Raises
    ------
    InputError
        A name that is not absolute, a name given twice, or not ``count`` names.
    """
    names = tuple(name.strip() for name in text.split(',') if name.strip())
    bad = [name for name in names if not name.startswith('/') or ' ' in name]
    if bad:
        raise InputError(f'{what}: {", ".join(bad)} is not an absolute topic name (/name)')
    if len(set(names)) != len(names):
        raise InputError(f'{what}: a topic is named twice in {text!r}')
    if count is not None and len(names) != count:
        raise InputError(f'{what}: expected {count} topics, got {len(names)} in {text!r}')
    return names


@dataclass(frozen=True)
class BagSource(os.PathLike):
    """A bag folder and the names its topics are read under.

    Parameters
    ----------
    path : the rosbag2 folder
    namespace : the vehicle namespace the contract topics are recorded under (``/auv1``)
    mag_topics : the four magnetometer topics in sensor order (overrides the namespace's)
    odom_topic : the odometry topic (overrides the namespace's)
    """

    path: str
    namespace: str = ''
    mag_topics: tuple[str, ...] = ()
    odom_topic: str = ''

    def __fspath__(self) -> str:
        return str(self.path)

    def __str__(self) -> str:
        return str(self.path)

    @property
    def names_topics(self) -> bool:
        return bool(self.namespace or self.mag_topics or self.odom_topic)

    def remap(self, recorded: Mapping[str, str]) -> dict[str, str]:
        """The bag's topic -> the contract's, from the names given; ``recorded`` is the bag's
        topic -> message type.

        Raises
        ------
        BagError
            A name given that the bag does not record, or a namespace under which it records
            no magnetometer.
        """
        rules: dict[str, str] = {}
        if self.namespace:
            ns = '/' + self.namespace.strip('/')
            rules = {ns + c: c for c in cv.CONTRACT_TOPICS if ns + c in recorded}
            if not any(c in cv.BAG_MAG_TOPICS for c in rules.values()):
                raise BagError(
                    f'{self.path}: --namespace {ns}: the bag records no magnetometer under it '
                    f'(expected {ns}{cv.BAG_MAG_TOPICS[0]}; the bag has: {_listing(recorded)})'
                )
        named = dict(zip(self.mag_topics, cv.BAG_MAG_TOPICS, strict=False))
        if self.odom_topic:
            named[self.odom_topic] = cv.ODOM_TOPIC
        rules = {t: c for t, c in rules.items() if c not in named.values()} | named
        return checked_remap(self.path, rules, recorded)


def checked_remap(
    path: str | os.PathLike, rules: Mapping[str, str], recorded: Mapping[str, str]
) -> dict[str, str]:
    """``rules`` (the bag's topic -> the contract's) when the bag records every topic they
    name with the contract topic's message type.

    Raises
    ------
    BagError
        Naming the topics the bag lacks or records with another type, and what it has.
    """
    missing = [t for t in rules if t not in recorded]
    if missing:
        raise BagError(
            f'{path}: no topic {", ".join(missing)} in the bag (it has: {_listing(recorded)})'
        )
    types = dict(zip(cv.CONTRACT_TOPICS, CONTRACT_TYPES, strict=True))
    wrong = [t for t, c in rules.items() if recorded[t] not in types[c]]
    if wrong:
        raise BagError(
            f'{path}: '
            + '; '.join(
                f'{t} holds {recorded[t]}, not {" or ".join(types[rules[t]])}' for t in wrong
            )
        )
    return dict(rules)


def namespaced(recorded: Mapping[str, str]) -> dict[str, str]:
    """Contract topics the bag records only under another namespace (``/auv1/tetra/mag1``
    for ``/tetra/mag1``, ``/auv1/odom`` for ``/odom``): the one recorded topic of the
    contract's type whose name ends in the contract's last name, mapped onto it. A name that
    ends so on two topics (two vehicles) is left unmapped: the contract check then names what
    the bag has."""
    assumed = {}
    for contract, msgtypes in zip(cv.CONTRACT_TOPICS, CONTRACT_TYPES, strict=True):
        if contract in recorded:
            continue
        last = '/' + contract.rsplit('/', 1)[-1]
        found = [t for t, m in recorded.items() if m in msgtypes and t.endswith(last)]
        if len(found) == 1 and found[0] not in assumed:
            assumed[found[0]] = contract
    return assumed


def _listing(recorded: Mapping[str, str], at_most: int = 12) -> str:
    names = sorted(recorded)
    shown = ', '.join(f'{t} ({recorded[t].rsplit("/", 1)[-1]})' for t in names[:at_most])
    return shown + (f' and {len(names) - at_most} more' if len(names) > at_most else '')
