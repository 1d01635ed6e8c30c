"""Authenticated calibrations: the calibrator signs what it writes and publishes,
the compensator adopts only what verifies.

HMAC-SHA256 (Python's :mod:`hmac` and :mod:`hashlib`: no home-made cryptography) with a
shared key read from a file (``calibration_key_file``, a read-only parameter of both nodes)
that only the suite's user may read: a key file with any group or other permission bit is
refused, as ssh refuses a private key.

What is signed is a canonical serialization of the calibration: the YAML document parsed
(so the signature does not depend on how the YAML is laid out), without its ``signature``
entry, as JSON with sorted keys and no spaces. Every entry is covered: ``k_soft``,
``b_hard_T``, ``sensor_noise_T``, the covariance, the terms, ``created_utc`` and the
diagnostics. The signature is one more top-level entry, appended to the text so everything
above it stays byte for byte what :meth:`CalibrationFile.to_yaml` wrote::

    signature:
      algorithm: HMAC-SHA256
      key_id: 3f2a...          # first 16 hex digits of SHA-256 of the key: which key signed
      value: 9c41...           # 64 hex digits

:class:`~tetra_gradiometer.io.calibration.CalibrationFile` ignores the entry, so a signed
file loads everywhere (the offline tools, a compensator without a key), and a file without
one loads wherever no key is configured.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import stat
from pathlib import Path
from typing import Any

import yaml

from ..errors import CalibrationFileError, ParamsError
from ..io._yaml import dumps, loads
from .common import ParamSpec, resolve_node_path
from .publishers import UNKNOWN_NODE, InputPublishers

ALGORITHM = 'HMAC-SHA256'
SIGNATURE_KEY = 'signature'
#: Shortest key accepted, bytes (the HMAC-SHA256 block of security: 256 bits).
MIN_KEY_BYTES = 32


class AuthenticationError(CalibrationFileError):
    """A calibration without a valid signature where a key is configured."""


def load_key(path: Path) -> bytes:
    """The key in ``path`` (its bytes, surrounding whitespace removed).

    Raises
    ------
    ParamsError
        The file is missing, not a regular file, readable or writable by group or others
        (``chmod 600`` it), or shorter than :data:`MIN_KEY_BYTES`.
    """
    try:
        mode = path.stat().st_mode
    except OSError as error:
        raise ParamsError(f'calibration_key_file {path}: {error.strerror}') from None
    if not stat.S_ISREG(mode):
        raise ParamsError(f'calibration_key_file {path} is not a regular file')
    if mode & 0o077:
        raise ParamsError(
            f'calibration_key_file {path} has mode {stat.S_IMODE(mode):04o}: group and others '
            f'must have no access (chmod 600 {path})'
        )
    key = path.read_bytes().strip()
    if len(key) < MIN_KEY_BYTES:
        raise ParamsError(
            f'calibration_key_file {path} holds {len(key)} bytes: at least {MIN_KEY_BYTES} '
            '(e.g. head -c 32 /dev/urandom | base64 > FILE)'
        )
    return key


def key_id(key: bytes) -> str:
    """Which key: the first 16 hex digits of its SHA-256 (says nothing usable about it)."""
    return hashlib.sha256(key).hexdigest()[:16]


def canonical(document: dict[str, Any]) -> bytes:
    """The bytes signed: ``document`` without its signature, as sorted, compact JSON."""
    unsigned = {k: v for k, v in document.items() if k != SIGNATURE_KEY}
    return json.dumps(unsigned, sort_keys=True, separators=(',', ':'), default=str).encode()


def _mac(document: dict[str, Any], key: bytes) -> str:
    return hmac.new(key, canonical(document), hashlib.sha256).hexdigest()


def _document(text: str, source: str) -> dict[str, Any]:
    try:
        document = loads(text)
    except yaml.YAMLError as error:
        raise CalibrationFileError(f'{source} is not valid YAML: {error}') from None
    if not isinstance(document, dict):
        raise CalibrationFileError(f'{source} is not a tetra_gradiometer calibration')
    return document


def sign(text: str, key: bytes) -> str:
    """``text`` (a calibration's YAML, unsigned) with its signature appended."""
    document = _document(text, 'the calibration to sign')
    signature = {'algorithm': ALGORITHM, 'key_id': key_id(key), 'value': _mac(document, key)}
    body = text if text.endswith('\n') else text + '\n'
    return body + dumps({SIGNATURE_KEY: signature})


def verify(text: str, key: bytes, source: str) -> None:
    """Check the signature of the calibration ``text`` against ``key``.

    Raises
    ------
    AuthenticationError
        No signature, another algorithm or key, or a value that does not match (the
        calibration was altered or forged).
    CalibrationFileError
        ``text`` is not YAML.
    """
    document = _document(text, source)
    signature = document.get(SIGNATURE_KEY)
    if not isinstance(signature, dict):
        raise AuthenticationError(f'{source} is not signed ({ALGORITHM} required)')
    if signature.get('algorithm') != ALGORITHM:
        raise AuthenticationError(
            f'{source} is signed with {signature.get("algorithm")!r}, not {ALGORITHM}'
        )
    if signature.get('key_id') != key_id(key):
        raise AuthenticationError(
            f'{source} is signed with another key (key id {signature.get("key_id")!r}, '
            f'ours {key_id(key)})'
        )
    value = signature.get('value')
    if not isinstance(value, str) or not hmac.compare_digest(value, _mac(document, key)):
        raise AuthenticationError(
            f'{source}: the signature does not match its content (altered or forged)'
        )


def key_file_spec(role: str) -> ParamSpec:
    """``calibration_key_file`` of the calibrator (``role`` 'signs') and compensator
    ('verifies')."""
    return ParamSpec(
        'calibration_key_file',
        '',
        f'File of the HMAC-SHA256 key with which this node {role} calibrations (shared by the '
        'calibrator and compensator; at least 32 bytes; mode 600: refused when group or '
        'others have access; "~" expanded, relative paths under $ROS_HOME). Empty: '
        'calibrations are unauthenticated (said on /diagnostics). Read-only.',
        read_only=True,
    )


def node_key(value: str) -> bytes | None:
    """The key a ``calibration_key_file`` value names (None: empty, unauthenticated)."""
    return load_key(resolve_node_path(value)) if value.strip() else None


class Refused(CalibrationFileError):
    """A calibration on the topic that the compensator does not adopt: the reason names
    the publishing nodes."""


#: How long a calibration may wait for the graph to name its publisher, s (discovery of a
#: node's name lags its endpoints by up to a few hundred ms on a loaded machine).
PUBLISHER_WAIT_S = 5.0


class CalibrationGate:
    """What the compensator adopts: a calibration on ``topic`` only while ``publisher`` (a
    fully qualified node name) is the only node publishing it, and with a ``key`` only
    when its signature verifies (files too); without a key, today's behaviour."""

    def __init__(self, watch: InputPublishers, topic: str, publisher: str, key: bytes | None):
        self.watch, self.topic, self.publisher, self.key = watch, topic, publisher, key

    @property
    def authentication(self) -> str:
        """For ``/diagnostics``: how calibrations are authenticated."""
        if self.key is None:
            return 'none: calibrations unauthenticated (no calibration_key_file)'
        return f'{ALGORITHM}, key id {key_id(self.key)}'

    def check_file(self, text: str, source: str) -> None:
        """Verify a calibration file's signature (nothing to do without a key).

        Raises
        ------
        AuthenticationError
            See :func:`verify`."""
        if self.key is not None:
            verify(text, self.key, source)

    def admit(self, text: str, waited_s: float) -> bool:
        """True when the calibration ``text`` that arrived on the topic ``waited_s`` ago may
        be adopted; False while the graph has not named its publisher yet (ask again).

        Raises
        ------
        Refused
            Another node publishes the topic, the publisher is not the configured one, or
            (with a key) the signature does not verify: the reason names the nodes."""
        names = self.watch.publishers(self.topic)
        known = [n for n in names if not n.endswith(UNKNOWN_NODE)]
        others = [n for n in known if n != self.publisher]
        if others:
            raise Refused(
                f'a calibration on {self.topic} while {", ".join(others)} also publish'
                f'{"es" if len(others) == 1 else ""} it (only {self.publisher} may)'
            )
        if len(known) > 1:  # a second node under the calibrator's name: which one sent it?
            raise Refused(
                f'a calibration on {self.topic} while {len(known)} nodes named '
                f'{self.publisher} publish it (one expected)'
            )
        if self.publisher not in known or len(known) < len(names):
            if waited_s < PUBLISHER_WAIT_S:
                return False
            listed = ', '.join(names) or 'none left in the graph'
            raise Refused(
                f'a calibration on {self.topic} not from {self.publisher} (publishers: {listed})'
            )
        if self.key is not None:
            try:
                verify(text, self.key, f'the calibration from {self.publisher}')
            except AuthenticationError as error:
                raise Refused(str(error)) from None
        return True
