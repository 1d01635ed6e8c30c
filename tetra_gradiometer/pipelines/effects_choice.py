"""Which effects a calibration may fit: automatic selection over the registry and the
declared signals, none, exactly the ones named, or the ones a discrepancy report named."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from ..core.effects import EFFECTS, SIGNAL_PREFIX, parse_declaration
from ..errors import InputError

__all__ = ['EffectsChoice']


@dataclass(frozen=True)
class EffectsChoice:
    """The effects a calibration may fit.

    Attributes
    ----------
    names : None for automatic selection; () for none; else exactly these effects
    current_topics : BatteryState topics read besides ``/battery_state``
    source : how it was chosen, for notes ('auto', 'none', '--effects', a report's path)
    signals : the declared signals' effect names (the params file's ``vehicle_signals``),
        candidates of the automatic selection beside the registry's
    discover : the automatic selection also offers every numeric signal a bag records
        beyond the contract, each in the basis :func:`~..core.effects.recorded_signal.
        basis_for` gives it (a declared signal keeps its declared basis)
    """

    names: tuple[str, ...] | None = None
    current_topics: tuple[str, ...] = ()
    source: str = 'auto'
    signals: tuple[str, ...] = ()
    discover: bool = True

    @property
    def signal_channels(self) -> tuple[str, ...]:
        """The signal channels to read: the declared signals', the signal effects named and
        those the registry's effects declare (an installed effect's) that may be fitted."""
        named = tuple(n for n in self.names or () if n.startswith(SIGNAL_PREFIX))
        declared = [parse_declaration(n).channel for n in (*self.signals, *named)]
        registry = [
            channel
            for name, effect in EFFECTS.items()
            if self.names is None or name in self.names
            for channel in effect.channels
            if channel.startswith(SIGNAL_PREFIX)
        ]
        return tuple(dict.fromkeys((*declared, *registry)))

    @classmethod
    def parse(cls, text: str, current_topics: tuple[str, ...] = ()) -> EffectsChoice:
        """``auto``, ``none`` or comma-separated registry names."""
        word = text.strip()
        if word == 'auto':
            return cls(None, current_topics, 'auto')
        if word == 'none':
            return cls((), current_topics, 'none')
        names = tuple(dict.fromkeys(n.strip() for n in word.split(',') if n.strip()))
        unknown = [n for n in names if n not in EFFECTS and not n.startswith(SIGNAL_PREFIX)]
        if unknown or not names:
            raise InputError(
                f'--effects {text!r}: {"unknown " + ", ".join(unknown) if unknown else "empty"};'
                f' choose auto, none or names of {", ".join(EFFECTS)}'
            )
        return cls(names, current_topics, '--effects')

    @classmethod
    def from_report(
        cls, path: str | os.PathLike[str], current_topics: tuple[str, ...] = ()
    ) -> EffectsChoice:
        """The registry effects a discrepancy ``report.json`` named (others it named, such as
        a time skew, are not vehicle effects a calibration carries: listed in the error when
        none is)."""
        try:
            document = json.loads(Path(path).read_text(encoding='utf-8'))
        except (OSError, ValueError) as error:
            raise InputError(f'--effects-from {path}: cannot read it: {error}') from None
        named = document.get('named_effects') if isinstance(document, dict) else None
        if not isinstance(named, list):
            raise InputError(f'--effects-from {path}: not a discrepancy report.json')
        names = tuple(
            dict.fromkeys(
                str(n) for n in named if n in EFFECTS or str(n).startswith(SIGNAL_PREFIX)
            )
        )
        return cls(names, current_topics, str(path))

    @property
    def automatic(self) -> bool:
        return self.names is None
