"""A phantom's channel layout: which cavities the board reads and which it loads, in order, made once
by the design and passed along to the model, the sensor chain, the estimator and every file.

- ``arms``: the sensing arms' cavities, in the sensor order;
- ``measured``: the internal cavities read as an arm is (a differential transducer each, their
  volume change by Boyle's law);
- ``actuated``: the internal cavities whose pressure is a load (an absolute transducer each: the
  BIP's urethra).

:attr:`ChannelLayout.sensing` (the arms, then the measured cavities) are the volume channels: the
rows of ``V`` and ``W``, the ``dV_*`` and ``dV*_*`` columns. :attr:`ChannelLayout.channels` is the
board's ADC order: the volume channels, then the actuated cavities' pressures.

Every writer puts :meth:`ChannelLayout.to_dict` under the metadata key :data:`LAYOUT_KEY`; every
reader takes it back with :func:`layout_in_meta`. A file of an older release has no such key: its
readers hand what it named to :func:`legacy_layout`, the one place where the BIP's names are
assumed.

>>> liver = ChannelLayout(("caudal", "cranial", "right", "left"), actuated=("tumour", "breathing"))
>>> liver.sensing, liver.channels[-2:]
(('caudal', 'cranial', 'right', 'left'), ('tumour', 'breathing'))
>>> ChannelLayout.from_dict(liver.to_dict()) == liver
True
>>> ChannelLayout(("a", "b", "a"))
Traceback (most recent call last):
...
ValueError: channel layout: 'a' named twice (each cavity once)
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from softphantom.errors import FileFormatError
from softphantom.records.names import ARM_NAMES, BIP_CAVITIES

LAYOUT_KEY = "channels"
"""The metadata key of the layout in every file (a JSON object; a JSON string of it in MCAP's
string-valued metadata)."""


def _names(what: str, value: Any) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, Iterable):
        raise ValueError(f"channel layout: {what} must be a list of names, got {value!r}")
    out = tuple(value)
    bad = [n for n in out if not (isinstance(n, str) and n and n.strip() == n and "," not in n)]
    if bad:
        raise ValueError(f"channel layout: {what}: {bad[0]!r} is not a name")
    return out


@dataclass(frozen=True)
class ChannelLayout:
    """The channels of a phantom (module docstring): ``arms``, ``measured`` and ``actuated``
    cavity names, each in order, each name once, at least one arm."""

    arms: tuple[str, ...]
    measured: tuple[str, ...] = ()
    actuated: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for what in ("arms", "measured", "actuated"):
            object.__setattr__(self, what, _names(what, getattr(self, what)))
        if not self.arms:
            raise ValueError("channel layout: no arm (at least one volume channel is read)")
        seen: set[str] = set()
        for n in self.channels:
            if n in seen:
                raise ValueError(f"channel layout: {n!r} named twice (each cavity once)")
            seen.add(n)

    @property
    def sensing(self) -> tuple[str, ...]:
        """The volume channels in the sensor order: the arms, then the measured cavities."""
        return (*self.arms, *self.measured)

    @property
    def channels(self) -> tuple[str, ...]:
        """The board's channels in ADC order: the volume channels, then the actuated cavities."""
        return (*self.sensing, *self.actuated)

    def to_dict(self) -> dict[str, list[str]]:
        """The metadata form (JSON): ``{"arms": [...], "measured": [...], "actuated": [...]}``."""
        return {"arms": list(self.arms), "measured": list(self.measured), "actuated": list(self.actuated)}

    @classmethod
    def from_dict(cls, d: Any, where: str = LAYOUT_KEY) -> "ChannelLayout":
        """Inverse of :meth:`to_dict`; a :class:`~softphantom.errors.FileFormatError` naming
        ``where`` (e.g. ``rec.csv: metadata channels``) for anything else."""
        if isinstance(d, str):
            try:
                d = json.loads(d)
            except ValueError:
                raise FileFormatError(f"{where}: not JSON: {d!r}") from None
        if not isinstance(d, Mapping):
            raise FileFormatError(f"{where}: expected an object with arms, measured, actuated, got {d!r}")
        unknown = sorted(set(d) - {"arms", "measured", "actuated"})
        if unknown:
            raise FileFormatError(f"{where}: unknown key {unknown[0]!r} (arms, measured, actuated)")
        if "arms" not in d:
            raise FileFormatError(f"{where}: no arms")
        try:
            return cls(d["arms"], d.get("measured", ()), d.get("actuated", ()))
        except ValueError as exc:
            raise FileFormatError(f"{where}: {str(exc).removeprefix('channel layout: ')}") from None

    def to_meta(self) -> dict[str, dict[str, list[str]]]:
        """``{LAYOUT_KEY: to_dict()}``, to merge into a file's metadata."""
        return {LAYOUT_KEY: self.to_dict()}

    def to_meta_str(self) -> dict[str, str]:
        """``{LAYOUT_KEY: JSON}``, for string-valued metadata (MCAP)."""
        return {LAYOUT_KEY: json.dumps(self.to_dict())}


class ChannelNames:
    """For a record that carries a ``layout``: its names, read from it (never stored apart)."""

    @property
    def arm_names(self) -> tuple[str, ...]:
        """The volume channels in the sensor order (the layout's ``sensing``: the arms, then the
        measured cavities): the columns of ``dp``/``dV``, the keys of ``volume_pred``/``volume_meas``."""
        return self.layout.sensing  # type: ignore[attr-defined]

    @property
    def cavity_names(self) -> tuple[str, ...]:
        """The actuated cavities (the layout's ``actuated``): the pressure channels, after the volume
        channels."""
        return self.layout.actuated  # type: ignore[attr-defined]


BIP_LAYOUT = ChannelLayout(ARM_NAMES, (), BIP_CAVITIES)
"""The BIP's: its four arms, no measured cavity, the urethra actuated."""


def layout_in_meta(meta: Mapping[str, Any], where: str = "metadata") -> ChannelLayout | None:
    """The layout a file's metadata names (:data:`LAYOUT_KEY`), None when it has none (a file of
    an older release: see :func:`legacy_layout`)."""
    if LAYOUT_KEY not in meta:
        return None
    return ChannelLayout.from_dict(meta[LAYOUT_KEY], f"{where} {LAYOUT_KEY}")


def legacy_layout(sensing: Iterable[str] | None = None, actuated: Iterable[str] | None = None) -> ChannelLayout:
    """The layout of a file written before the layout entered the metadata, from what it named:
    ``sensing`` its volume channels (older files cannot tell a measured cavity from an arm: all are
    arms), ``actuated`` its pressure channels; either unnamed (None or empty volume channels) is the
    BIP's. The one place where the BIP's names are assumed.

    >>> legacy_layout() == BIP_LAYOUT, legacy_layout(("a", "b", "c"), ()).channels
    (True, ('a', 'b', 'c'))
    """
    arms = tuple(sensing) if sensing else ARM_NAMES
    return ChannelLayout(arms, (), BIP_CAVITIES if actuated is None else tuple(actuated))


def read_layout(meta: Mapping[str, Any], where: str = "metadata", *, sensing: Iterable[str] | None = None,
                actuated: Iterable[str] | None = None) -> ChannelLayout:
    """A file's layout: its metadata's (:func:`layout_in_meta`), else (an older file's)
    :func:`legacy_layout` of the names it gave (``sensing``, ``actuated``)."""
    got = layout_in_meta(meta, where)
    return got if got is not None else legacy_layout(sensing, actuated)
