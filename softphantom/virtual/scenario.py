"""Scripted interactions of the virtual phantom: TOML scenario files (units in every key name).

A scenario is a rest window (the tare) followed by *events*, each a smooth load ramp from rest to
a peak, a hold at the peak and a ramp back to rest (quasi-static, so a ramp's shape in time does
not change the equilibria it passes through):

* ``[[push]]`` a force (N, model frame) at a contact point of the model (``on-centre``,
  ``off-centre`` or one of its design's ``[contacts]``: :meth:`Scenario.check_points`), spread over
  a small surface patch (a point force is singular in 3-D; DESIGN.md §5);
* ``[[inflate]]`` the gauge pressure of an internal cavity (``cavity = "NAME"``; default the
  design's only one, the BIP's urethra: :meth:`Scenario.check_cavities`): either ``p_kPa``
  given, or inflated *until* a named target moves ``target_shift_mm`` (DESIGN.md §5: the paper's
  marker next to the urethra moved ≈ 2 mm), capped at ``max_p_kPa`` (the transducer's or the
  silicone's limit); ``p_urethra_kPa`` and ``max_p_urethra_kPa`` are read as their synonyms.

An event may happen ``repeat`` times, each ``period_s`` after the previous start (breathing: an
inflation every 4 s); each occurrence is the same load path. Two events may act at once (a
*group*: a push during an inflation, :attr:`Scenario.groups`): their loads add. Three at once, or
an inflation until a target moves inside a group (its peak is found by a march from rest alone),
are refused. Each event alone is a one-parameter load path from rest (its *level* s ∈ [0, 1] times
its peak); a group, a two-parameter one. Example (``scenarios/needle-insertion.toml``)::

    name = "needle-insertion"
    duration_s = 12.0
    rest_s = 1.5
    [[push]]
    point = "on-centre"
    start_s = 2.0
    rise_s = 4.0
    hold_s = 2.0
    fall_s = 2.5
    force_N = [0.15, 3.0, -0.25]
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import field_validator, model_validator

from softphantom.errors import UserError
from softphantom.fem.contact import DEFAULT_CONTACT_RADIUS_M
from softphantom.schema import Field, FileModel, Vec3, between, parse, refuse

POINTS = ("on-centre", "off-centre")  # every model's; a design's [contacts] add to them
MAX_DURATION_S = 600.0
"""Longest scenario: the board is modelled on a 1 kHz grid (about 20 float columns, ~0.16 MB per
second), so 10 min is ~100 MB; 1e9 s asked for terabytes."""
BUNDLED = ("needle-insertion", "push-on-centre", "push-off-centre", "urethra-inflation")
"""The four scenarios of the paper's Sec. V (Figs. 8–11), in ``scenarios/`` of the repository."""


class ScenarioError(UserError):
    """A scenario file that cannot be used (names the file and the key)."""


@dataclass(frozen=True)
class Event:
    """One load ramp: ``kind`` "push" or "inflate"; times in s; ``force_N`` (3,) peak for a push;
    for an inflation of internal cavity ``cavity`` (None: the design's only one) ``p_kPa`` (peak,
    or None to inflate until ``target`` moved ``target_shift_mm``, at most ``max_p_kPa``)."""

    kind: str
    start_s: float
    rise_s: float
    hold_s: float
    fall_s: float
    point: str = "on-centre"
    force_N: tuple[float, float, float] = (0.0, 0.0, 0.0)
    p_kPa: float | None = None
    target: str | None = None
    target_shift_mm: float | None = None
    max_p_kPa: float = 150.0
    cavity: str | None = None
    repeat: int = 1
    period_s: float | None = None

    @property
    def end_s(self) -> float:
        """The end of its last occurrence."""
        return self.starts_s[-1] + self.rise_s + self.hold_s + self.fall_s

    @property
    def starts_s(self) -> tuple[float, ...]:
        """The start of each occurrence.

        >>> Event("inflate", 2.0, 1.0, 0.5, 1.0, repeat=3, period_s=4.0).starts_s
        (2.0, 6.0, 10.0)
        """
        if self.repeat == 1:
            return (self.start_s,)
        return tuple(self.start_s + k * self.period_s for k in range(self.repeat))

    def _local(self, t: np.ndarray) -> np.ndarray:
        """``t`` moved into the occurrence it falls in (the first before it, the last after it)."""
        if self.repeat == 1:
            return t
        k = np.clip(np.floor((t - self.start_s) / self.period_s), 0, self.repeat - 1)
        return t - k * self.period_s

    def acting(self, t) -> np.ndarray:
        """Whether one of its occurrences acts at ``t`` (its ends included)."""
        t = self._local(np.asarray(t, float))
        return (t >= self.start_s) & (t <= self.start_s + self.rise_s + self.hold_s + self.fall_s)

    def level(self, t) -> np.ndarray:
        """Load level s(t) ∈ [0, 1]: cosine ramps (zero rate at both ends), hold at 1; the same in
        every occurrence.

        >>> e = Event("inflate", 2.0, 1.0, 0.0, 1.0, repeat=2, period_s=4.0)
        >>> e.level([3.0, 5.0, 7.0, 9.0]).tolist()
        [1.0, 0.0, 1.0, 0.0]
        """
        t = self._local(np.asarray(t, float))
        up = np.clip((t - self.start_s) / self.rise_s, 0.0, 1.0)
        down = np.clip((t - self.start_s - self.rise_s - self.hold_s) / self.fall_s, 0.0, 1.0)
        return 0.5 * (1.0 - np.cos(np.pi * up)) - 0.5 * (1.0 - np.cos(np.pi * down))


@dataclass(frozen=True)
class Scenario:
    """A validated scenario: ``duration_s``, ``rest_s`` at rest at the start (the tare window),
    ``patch_radius_mm`` of a push's contact patch, ``events`` in time order."""

    name: str
    description: str
    duration_s: float
    rest_s: float
    events: tuple[Event, ...]
    patch_radius_mm: float = DEFAULT_CONTACT_RADIUS_M * 1e3
    source: str = ""

    def check_points(self, names) -> "Scenario":
        """The scenario if every push is at one of ``names`` (a model's contact points, its
        ``p_ext``), else a one-line :class:`ScenarioError` naming the file and listing them.

        >>> sc = scenario_from_dict({"name": "n", "duration_s": 3, "push": [
        ...     {"point": "front-lobe", "start_s": 1, "rise_s": 1, "force_N": [0, 1, 0]}]}, "n.toml")
        >>> sc.check_points(POINTS)
        Traceback (most recent call last):
        ...
        softphantom.virtual.scenario.ScenarioError: n.toml: push.point front-lobe: not a contact point of this model (on-centre, off-centre)
        """
        names = list(names)
        for e in self.events:
            if e.kind == "push" and e.point not in names:
                raise ScenarioError(f"{self.source}: push.point {e.point}: not a contact point of this model "
                                    f"({', '.join(names)})")
        return self

    def check_cavities(self, names) -> "Scenario":
        """The scenario with each inflation's cavity named, checked against ``names`` (a model's
        internal cavities): an inflation without ``cavity`` inflates the only one; otherwise a
        one-line :class:`ScenarioError` naming the file and the choices.

        >>> sc = scenario_from_dict({"name": "n", "duration_s": 3, "inflate": [
        ...     {"p_kPa": 20, "start_s": 1, "rise_s": 1}]}, "n.toml")
        >>> sc.check_cavities(["urethra"]).events[0].cavity
        'urethra'
        >>> sc.check_cavities(["urethra", "tumour"])
        Traceback (most recent call last):
        ...
        softphantom.virtual.scenario.ScenarioError: n.toml: inflate.cavity: missing; this model has several internal cavities (urethra, tumour): name one
        """
        names = list(names)
        have = ", ".join(names) or "none"
        events = []
        for e in self.events:
            if e.kind == "inflate":
                if e.cavity is None and len(names) != 1:
                    raise ScenarioError(f"{self.source}: inflate.cavity: missing; this model has "
                                        + (f"several internal cavities ({have}): name one" if names
                                           else "no internal cavity to inflate"))
                if e.cavity is not None and e.cavity not in names:
                    raise ScenarioError(f"{self.source}: inflate.cavity {e.cavity}: not an internal cavity of this "
                                        f"model ({have})")
                e = replace(e, cavity=e.cavity or names[0])
            events.append(e)
        return replace(self, events=tuple(events))

    def active(self, t: float) -> int | None:
        """Index of the first event acting at ``t`` (None at rest)."""
        for i, e in enumerate(self.events):
            if e.acting(t):
                return i
        return None

    @property
    def groups(self) -> tuple[tuple[int, int], ...]:
        """The pairs (i, j), i < j, of events (indices into ``events``) that act at once at some
        time: each is one two-parameter load path of the truth.

        >>> sc = scenario_from_dict({"name": "n", "duration_s": 20, "inflate": [{"p_kPa": 20,
        ...     "start_s": 2, "rise_s": 1.5, "fall_s": 1.5, "repeat": 4, "period_s": 4}], "push": [
        ...     {"start_s": 3, "rise_s": 4, "hold_s": 8, "force_N": [0, 2, 0]}]}, "n.toml")
        >>> [e.kind for e in sc.events], sc.groups
        (['inflate', 'push'], ((0, 1),))
        """
        return _overlapping_pairs(_occurrences(self.events))


_PATCH_MM = DEFAULT_CONTACT_RADIUS_M * 1e3
Seconds = Annotated[float, Field(ge=0)]
Positive = Annotated[float, Field(gt=0)]


class _Times(FileModel):
    start_s: Seconds
    rise_s: Positive
    hold_s: Seconds = 0.0
    fall_s: Positive | None = None  # default: rise_s
    repeat: Annotated[int, Field(ge=1)] = 1
    period_s: Positive | None = None  # required when repeat > 1

    @model_validator(mode="after")
    def _period(self):
        if self.repeat > 1 and self.period_s is None:
            raise refuse(f"repeat = {self.repeat} needs period_s (s from one start to the next)")
        one = self.rise_s + self.hold_s + (self.fall_s or self.rise_s)
        if self.period_s is not None and self.period_s < one:
            raise refuse(f"period_s = {self.period_s:g} s is shorter than the event (rise_s + hold_s + fall_s "
                         f"= {one:g} s)")
        return self

    def times(self) -> dict:
        rep = dict(repeat=self.repeat, period_s=self.period_s) if self.repeat > 1 else {}
        return dict(start_s=self.start_s, rise_s=self.rise_s, hold_s=self.hold_s, fall_s=self.fall_s or self.rise_s,
                    **rep)


class _Push(_Times):
    point: str = "on-centre"  # a contact point's name, checked against a model's (Scenario.check_points)
    force_N: Vec3

    @field_validator("point")
    @classmethod
    def _name(cls, p: str) -> str:
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", p):
            raise refuse("must be a contact point's name (a letter, then letters, digits, _ or -)")
        return p

    @field_validator("force_N")
    @classmethod
    def _magnitude(cls, f: list) -> list:
        if not 0 < math.hypot(*f) <= 20.0:
            raise refuse(f"has magnitude {math.hypot(*f):.3g} N, outside (0, 20] N")
        return f


MaxPressure = Annotated[float, between(0, 250, "kPa (the MPX4250D's range)", above=True)]


class _Inflate(_Times):
    cavity: str | None = Field(None, min_length=1)
    p_kPa: Positive | None = None
    p_urethra_kPa: Positive | None = None  # the BIP's files: p_kPa's synonym
    target: str | None = Field(None, min_length=1)
    target_shift_mm: Positive = 2.0
    max_p_kPa: MaxPressure | None = None
    max_p_urethra_kPa: MaxPressure | None = None  # max_p_kPa's synonym

    @model_validator(mode="after")
    def _one_of(self):
        for a, b in (("p_kPa", "p_urethra_kPa"), ("max_p_kPa", "max_p_urethra_kPa")):
            if getattr(self, a) is not None and getattr(self, b) is not None:
                raise refuse(f"give {a} or its synonym {b}, not both")
        p, p_key = (self.p_kPa, "p_kPa") if self.p_urethra_kPa is None else (self.p_urethra_kPa, "p_urethra_kPa")
        if (p is None) == (self.target is None):
            raise refuse("give either p_kPa / p_urethra_kPa or target (+ target_shift_mm)")
        mx = self.max_pressure_kPa
        if p is not None and p > mx:
            bip = self.max_p_urethra_kPa is not None or p_key == "p_urethra_kPa"
            mx_key = "max_p_urethra_kPa" if bip else "max_p_kPa"
            raise refuse(f"{p_key} = {p:g} kPa is above {mx_key} {mx:g}")
        return self

    @property
    def pressure_kPa(self) -> float | None:
        return self.p_kPa if self.p_urethra_kPa is None else self.p_urethra_kPa

    @property
    def max_pressure_kPa(self) -> float:
        return next((v for v in (self.max_p_kPa, self.max_p_urethra_kPa) if v is not None), 150.0)


class _ScenarioFile(FileModel):
    name: str = Field(min_length=1)
    description: str = ""
    duration_s: Annotated[float, between(0, MAX_DURATION_S, "s", above=True)]
    rest_s: Positive = 1.0
    patch_radius_mm: Positive = _PATCH_MM
    push: list[_Push] = []
    inflate: list[_Inflate] = []


def scenario_from_dict(d: dict, source: str = "<dict>") -> Scenario:
    """Validate a parsed scenario; raises :class:`ScenarioError` (one line, names file and key)."""
    f = parse(_ScenarioFile, d, ScenarioError, source=source)
    events = [Event("push", point=e.point, force_N=tuple(e.force_N), **e.times()) for e in f.push]
    events += [Event("inflate", p_kPa=e.pressure_kPa, target=e.target,
                     target_shift_mm=None if e.target is None else e.target_shift_mm,
                     max_p_kPa=e.max_pressure_kPa, cavity=e.cavity, **e.times()) for e in f.inflate]
    if not events:
        raise ScenarioError(f"{source}: no [[push]] or [[inflate]] event")
    events.sort(key=lambda e: e.start_s)
    if events[0].start_s < f.rest_s:
        raise ScenarioError(f"{source}: the first event starts at {events[0].start_s:g} s, inside the "
                            f"rest (tare) window of {f.rest_s:g} s")
    for e in events:
        if e.repeat > 1 and e.end_s > f.duration_s:  # before its occurrences are listed
            raise ScenarioError(f"{source}: {e.kind}.repeat: the {e.kind} at {e.start_s:g} s repeated {e.repeat} "
                                f"times ends at {e.end_s:g} s, after duration_s {f.duration_s:g}")
    occ = _occurrences(events)
    for a, b, c in _triples(occ):
        raise ScenarioError(f"{source}: three events act at once ({_name(events, a)}, {_name(events, b)}, "
                            f"{_name(events, c)}): at most two may overlap")
    for i, j in _overlapping_pairs(occ):
        for k, o in ((i, j), (j, i)):
            if events[k].kind == "inflate" and events[k].p_kPa is None:
                raise ScenarioError(f"{source}: inflate.target_shift_mm: an inflation until {events[k].target} "
                                    f"moves cannot overlap another event (the inflate at "
                                    f"{events[k].start_s:g} s, the {events[o].kind} at {events[o].start_s:g} s); "
                                    f"give p_kPa")
    if events[-1].end_s > f.duration_s:
        raise ScenarioError(f"{source}: the last event ends at {events[-1].end_s:g} s, after duration_s {f.duration_s:g}")
    return Scenario(f.name, f.description, f.duration_s, f.rest_s, tuple(events), f.patch_radius_mm, source)


def _occurrences(events) -> list[tuple[float, float, int]]:
    """(start, end, event index) of every occurrence, by start."""
    d = [e.rise_s + e.hold_s + e.fall_s for e in events]
    return sorted((s, s + d[i], i) for i, e in enumerate(events) for s in e.starts_s)


def _overlapping_pairs(occ) -> tuple[tuple[int, int], ...]:
    """The pairs of events two of whose occurrences overlap (touching ends do not)."""
    pairs = set()
    for n, (s, end, i) in enumerate(occ):
        for s2, _, j in occ[n + 1:]:
            if s2 >= end:
                break
            if i != j:
                pairs.add((min(i, j), max(i, j)))
    return tuple(sorted(pairs))


def _triples(occ):
    """Three occurrences acting at once (the latest-starting one starts inside both others)."""
    live: list = []  # the occurrences still acting (at most two, or this yields)
    for o in occ:
        live = [x for x in live if x[1] > o[0]]
        if len(live) >= 2:
            yield live[0], live[1], o
        live.append(o)


def _name(events, occ) -> str:
    e = events[occ[2]]
    return f"{e.kind}" + (f" {e.cavity}" if e.kind == "inflate" and e.cavity else "") + f" at {occ[0]:g} s"


def scenarios_dir() -> Path:
    """The repository's ``scenarios/`` directory (bundled scenario files)."""
    return Path(__file__).resolve().parents[2] / "scenarios"


def load_scenario(spec: str | Path) -> Scenario:
    """A scenario from a TOML file path, or by the name of a bundled one (:data:`BUNDLED`)."""
    p = Path(spec)
    if not p.is_file():
        cand = scenarios_dir() / f"{spec}.toml"
        if cand.is_file():
            p = cand
        elif p.suffix == ".toml" or "/" in str(spec):
            raise ScenarioError(f"scenario {spec}: no such file")
        else:
            raise ScenarioError(f"scenario {spec!r}: not a file nor a bundled scenario ({', '.join(BUNDLED)})")
    try:
        d = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{p}: not valid TOML ({exc})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{p}: cannot read ({exc})") from None
    return scenario_from_dict(d, str(p))
