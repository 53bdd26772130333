"""Scripted interactions of the virtual phantom: TOML scenario files (units in every key name).

A scenario is a rest window (the tare) followed by *events*, each a smooth load ramp from rest to
a peak, a hold at the peak and a ramp back to rest (quasi-static, so a ramp's shape in time does
not change the equilibria it passes through):

* ``[[push]]`` a force (N, model frame) at an interaction point (``on-centre`` / ``off-centre``),
  spread over a small surface patch (a point force is singular in 3-D; DESIGN.md §5);
* ``[[inflate]]`` a urethra gauge pressure: either ``p_urethra_kPa`` given, or inflated *until* a
  named target moves ``target_shift_mm`` (DESIGN.md §5: the paper's marker next to the urethra
  moved ≈ 2 mm), capped at ``max_p_urethra_kPa`` (the transducer's or the silicone's limit).

Events do not overlap in time, so each one is a one-parameter load path from rest (its *level*
s ∈ [0, 1] times its peak). Example (``scenarios/needle-insertion.toml``)::

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
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softphantom.errors import UserError
from softphantom.fem.contact import DEFAULT_CONTACT_RADIUS_M

POINTS = ("on-centre", "off-centre")
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
    for an inflation ``p_urethra_kPa`` (peak, or None to inflate until ``target`` moved
    ``target_shift_mm``, at most ``max_p_urethra_kPa``)."""

    kind: str
    start_s: float
    rise_s: float
    hold_s: float
    fall_s: float
    point: str = "on-centre"
    force_N: tuple[float, float, float] = (0.0, 0.0, 0.0)
    p_urethra_kPa: float | None = None
    target: str | None = None
    target_shift_mm: float | None = None
    max_p_urethra_kPa: float = 150.0

    @property
    def end_s(self) -> float:
        return self.start_s + self.rise_s + self.hold_s + self.fall_s

    def level(self, t) -> np.ndarray:
        """Load level s(t) ∈ [0, 1]: cosine ramps (zero rate at both ends), hold at 1."""
        t = np.asarray(t, float)
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

    def active(self, t: float) -> int | None:
        """Index of the event acting at ``t`` (None at rest)."""
        for i, e in enumerate(self.events):
            if e.start_s <= t <= e.end_s:
                return i
        return None


_TOP = {"name", "description", "duration_s", "rest_s", "patch_radius_mm", "push", "inflate"}
_TIMES = ("start_s", "rise_s", "hold_s", "fall_s")
_PUSH = set(_TIMES) | {"point", "force_N"}
_INFLATE = set(_TIMES) | {"p_urethra_kPa", "target", "target_shift_mm", "max_p_urethra_kPa"}


def _num(where: str, v, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ScenarioError(f"{where}: expected a number, got {v!r}")
    v = float(v)
    if positive and not v > 0:
        raise ScenarioError(f"{where}: must be > 0, got {v:g}")
    if nonneg and v < 0:
        raise ScenarioError(f"{where}: must be >= 0, got {v:g}")
    return v


def _check_keys(where: str, table: dict, allowed: set, required: tuple[str, ...]) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ScenarioError(f"{where}: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(sorted(allowed))})")
    for k in required:
        if k not in table:
            raise ScenarioError(f"{where}: missing key {k!r}")


def scenario_from_dict(d: dict, source: str = "<dict>") -> Scenario:
    """Validate a parsed scenario; raises :class:`ScenarioError` (one line, names file and key)."""
    if not isinstance(d, dict):
        raise ScenarioError(f"{source}: expected a table at the top level")
    _check_keys(source, d, _TOP, ("name", "duration_s"))
    name = d["name"]
    if not isinstance(name, str) or not name:
        raise ScenarioError(f"{source}: name: expected a non-empty string")
    duration = _num(f"{source}: duration_s", d["duration_s"], positive=True)
    if duration > MAX_DURATION_S:
        raise ScenarioError(f"{source}: duration_s = {duration:g} s is above the limit of {MAX_DURATION_S:g} s")
    rest = _num(f"{source}: rest_s", d.get("rest_s", 1.0), positive=True)
    patch = _num(f"{source}: patch_radius_mm", d.get("patch_radius_mm", DEFAULT_CONTACT_RADIUS_M * 1e3), positive=True)
    events: list[Event] = []
    for kind, allowed in (("push", _PUSH), ("inflate", _INFLATE)):
        items = d.get(kind, [])
        if not isinstance(items, list):
            raise ScenarioError(f"{source}: {kind}: expected [[{kind}]] tables")
        for i, e in enumerate(items):
            where = f"{source}: {kind}[{i}]"
            if not isinstance(e, dict):
                raise ScenarioError(f"{where}: expected a table")
            _check_keys(where, e, allowed, ("start_s", "rise_s"))
            times = dict(
                start_s=_num(f"{where}.start_s", e["start_s"], nonneg=True),
                rise_s=_num(f"{where}.rise_s", e["rise_s"], positive=True),
                hold_s=_num(f"{where}.hold_s", e.get("hold_s", 0.0), nonneg=True),
                fall_s=_num(f"{where}.fall_s", e.get("fall_s", e["rise_s"]), positive=True),
            )
            if kind == "push":
                point = e.get("point", "on-centre")
                if point not in POINTS:
                    raise ScenarioError(f"{where}.point: {point!r} is not one of {', '.join(POINTS)}")
                f = e.get("force_N")
                if not isinstance(f, list) or len(f) != 3:
                    raise ScenarioError(f"{where}.force_N: expected [fx, fy, fz] in newtons, got {f!r}")
                fv = tuple(_num(f"{where}.force_N[{k}]", x) for k, x in enumerate(f))
                if not 0 < math.hypot(*fv) <= 20.0:
                    raise ScenarioError(f"{where}.force_N: magnitude {math.hypot(*fv):.3g} N outside (0, 20] N")
                events.append(Event("push", point=point, force_N=fv, **times))
            else:
                p = e.get("p_urethra_kPa")
                target = e.get("target")
                pmax = _num(f"{where}.max_p_urethra_kPa", e.get("max_p_urethra_kPa", 150.0), positive=True)
                if pmax > 250.0:
                    raise ScenarioError(f"{where}.max_p_urethra_kPa: {pmax:g} kPa beyond the MPX4250D's 250 kPa")
                if (p is None) == (target is None):
                    raise ScenarioError(f"{where}: give either p_urethra_kPa or target (+ target_shift_mm)")
                if p is not None:
                    p = _num(f"{where}.p_urethra_kPa", p, positive=True)
                    if p > pmax:
                        raise ScenarioError(f"{where}.p_urethra_kPa: {p:g} kPa above max_p_urethra_kPa {pmax:g}")
                    events.append(Event("inflate", p_urethra_kPa=p, max_p_urethra_kPa=pmax, **times))
                else:
                    if not isinstance(target, str) or not target:
                        raise ScenarioError(f"{where}.target: expected a target name")
                    shift = _num(f"{where}.target_shift_mm", e.get("target_shift_mm", 2.0), positive=True)
                    events.append(Event("inflate", target=target, target_shift_mm=shift,
                                        max_p_urethra_kPa=pmax, **times))
    if not events:
        raise ScenarioError(f"{source}: no [[push]] or [[inflate]] event")
    events.sort(key=lambda e: e.start_s)
    if events[0].start_s < rest:
        raise ScenarioError(f"{source}: the first event starts at {events[0].start_s:g} s, inside the "
                            f"rest (tare) window of {rest:g} s")
    for a, b in zip(events, events[1:]):
        if b.start_s < a.end_s:
            raise ScenarioError(f"{source}: events overlap ({a.kind} ends at {a.end_s:g} s, the next "
                                f"{b.kind} starts at {b.start_s:g} s)")
    if events[-1].end_s > duration:
        raise ScenarioError(f"{source}: the last event ends at {events[-1].end_s:g} s, after duration_s {duration:g}")
    desc = d.get("description", "")
    if not isinstance(desc, str):
        raise ScenarioError(f"{source}: description: expected a string")
    return Scenario(name, desc, duration, rest, tuple(events), patch, source)


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
