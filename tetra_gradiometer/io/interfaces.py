"""Our ROS interfaces (the package ``tetra_gradiometer_msgs``) for rosbags, without ROS.

The offline tools read and write bags with rosbags, which needs a message's definition and
not its compiled package: :func:`register` parses the package's ``.msg`` and ``.srv`` text
(``rosbags.typesys.get_types_from_msg``; a service as its ``_Request`` and ``_Response``
messages, as rosidl names them) and adds the types to a rosbags typestore.
:func:`tetra_gradiometer.io.bag.typestore` does so for every reader and writer (when the
definitions are found: else the standard types alone, as before).

Where the definitions are read from, the first that has them:

1. the checkout: ``tetra_gradiometer_msgs/`` beside this Python package (a source tree,
   and the venv of ``make setup``, which puts the checkout on its path); the source of
   truth, so an edited ``.msg`` is seen before it is rebuilt;
2. the installed interface package: ``share/tetra_gradiometer_msgs/{msg,srv}`` under each
   prefix of ``AMENT_PREFIX_PATH`` (a colcon install, a ROS install) and under
   ``sys.prefix`` (``make setup`` installs it into the venv's prefix).

The Python package installed by colcon lies in ``install/.../site-packages``, with no
``tetra_gradiometer_msgs/`` beside it: there the second place answers. Nothing is copied into
this package's data, so there is one set of definitions.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path
from typing import Any

from rosbags.typesys import get_types_from_msg

from ..errors import InputError

PACKAGE = 'tetra_gradiometer_msgs'
#: The interfaces, by file stem (msg/NAME.msg, srv/NAME.srv).
MESSAGES = ('GradientTensor', 'Calibration')
SERVICES = ('Calibrate',)


class InterfacesNotFound(InputError):
    """The definitions of ``tetra_gradiometer_msgs`` are in none of the places searched."""


def candidate_dirs() -> list[Path]:
    """The folders searched for the package, in order (see the module docstring)."""
    dirs = [Path(__file__).resolve().parents[2] / PACKAGE]
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    dirs += [Path(p) / 'share' / PACKAGE for p in (*prefixes, sys.prefix)]
    return dirs


def _complete(folder: Path) -> bool:
    files = [f'msg/{m}.msg' for m in MESSAGES] + [f'srv/{s}.srv' for s in SERVICES]
    return all((folder / f).is_file() for f in files)


def package_dir() -> Path:
    """The first searched folder holding every ``.msg`` and ``.srv`` of the package."""
    dirs = candidate_dirs()
    for folder in dirs:
        if _complete(folder):
            return folder
    raise InterfacesNotFound(
        f'the {PACKAGE} definitions are in none of: {", ".join(map(str, dirs))} '
        f'(a checkout has them; else build and install the package: make setup or colcon)'
    )


def split_service(text: str) -> tuple[str, str]:
    """A ``.srv`` text's request and response parts (split at the line ``---``)."""
    lines = text.splitlines()
    cuts = [i for i, line in enumerate(lines) if line.strip() == '---']
    if len(cuts) != 1:
        raise InputError(f'a service definition has one --- line, this one has {len(cuts)}')
    cut = cuts[0]
    return '\n'.join(lines[:cut]) + '\n', '\n'.join(lines[cut + 1 :]) + '\n'


def types_from(folder: Path) -> dict[str, Any]:
    """rosbags' parse of every interface in ``folder``: type name -> definition."""
    types: dict[str, Any] = {}
    for name in MESSAGES:
        text = (folder / 'msg' / f'{name}.msg').read_text()
        types.update(get_types_from_msg(text, f'{PACKAGE}/msg/{name}'))
    for name in SERVICES:
        parts = split_service((folder / 'srv' / f'{name}.srv').read_text())
        for part, text in zip(('Request', 'Response'), parts, strict=True):
            # rosbags' .msg parser files every type under msg/: named as rosidl does here
            ((_, definition),) = get_types_from_msg(text, f'{PACKAGE}/{name}_{part}').items()
            types[f'{PACKAGE}/srv/{name}_{part}'] = definition
    return types


@functools.cache
def interface_types() -> dict[str, Any]:
    """The definitions of :func:`package_dir` (read once per process)."""
    return types_from(package_dir())


def register(store: Any, *, missing_ok: bool = False) -> Any:
    """Add our interfaces to the rosbags typestore ``store`` (returned, for chaining).

    With ``missing_ok`` a store is returned as it was when the definitions are not found (the
    offline tools of an install without the package still read and write the standard
    types; a message of ours then fails as any type rosbags does not know).

    Raises
    ------
    InterfacesNotFound
        The definitions are in none of :func:`candidate_dirs` (unless ``missing_ok``).
    """
    try:
        types = interface_types()
    except InterfacesNotFound:
        if missing_ok:
            return store
        raise
    store.register(types)
    return store
