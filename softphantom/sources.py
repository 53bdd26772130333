"""Every ``--source`` in one registry, one meaning per scheme.

========================  ==========================================================  ============
``--source``              what it opens                                               gives
========================  ==========================================================  ============
``serial:PORT``           the sensing board (tared on its first ``tare_s`` at rest)   measurements
``replay:FILE``           a recorded file, at the level it was recorded: a sensing    measurements
                          recording (``acquire --out``) gives its samples; a session  or estimates
                          recording (``.mcap``) or an estimate file its estimates
``virtual:SCENARIO``      the virtual phantom running a scenario (its board's frames) measurements
``synthetic``             made-up estimates for trying the live view                  estimates
========================  ==========================================================  ============

:func:`open_source` gives an :class:`~softphantom.sensing.bench.OpenedSource`; its ``gives`` says
whether ``source`` is a :class:`~softphantom.sensing.sources.SensorSource` (run it through an
estimator) or an estimate source of the live view. The implementations stay with their stages
(:mod:`softphantom.sensing.bench`, :mod:`softphantom.virtual`, :mod:`softphantom.viz.live`); this
module sits above them and only dispatches.

>>> sorted(SOURCES)
['replay', 'serial', 'synthetic', 'virtual']
>>> open_source("bogus:x")
Traceback (most recent call last):
...
softphantom.errors.UserError: unknown --source 'bogus:x' (unknown kind 'bogus'); use serial:PORT, replay:FILE, virtual:SCENARIO or synthetic
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softphantom.errors import UserError
from softphantom.sensing.bench import OpenedSource, open_replay, open_serial


@dataclass(frozen=True)
class SourceKind:
    """A registry entry: ``scheme`` (before the colon), ``usage`` as the user writes it, what it
    ``gives`` (``measurements``, ``estimates``, or ``recorded``: what the file holds), a
    ``description``, and ``open(arg, **settings) -> OpenedSource``."""

    scheme: str
    usage: str
    gives: str
    description: str
    open: Callable[..., OpenedSource]


def _serial(arg: str, *, model=None, bench=None, options=None, tare_s=1.0, on_new_board="stop",
            connect_timeout_s=5.0, baud=115_200, osr=None, serial_opener=None, **_) -> OpenedSource:
    return open_serial(arg, _model(model), bench, options=options, tare_s=tare_s, on_new_board=on_new_board,
                       connect_timeout_s=connect_timeout_s, baud=baud, osr=osr, serial_opener=serial_opener)


def _virtual(arg: str, *, model=None, bench=None, options=None, **_) -> OpenedSource:
    from softphantom.sensing.bench import BenchConfig

    try:
        from softphantom.virtual import sensor_source
    except ImportError:
        raise UserError("--source virtual:…: the virtual phantom (softphantom.virtual) is not available "
                        "in this installation") from None
    model = _model(model)
    if model is None:
        raise UserError(f"--source virtual:{arg} needs --model DIR (a model directory from softphantom design)")
    from softphantom.virtual.run import scenario_contact
    from softphantom.virtual.scenario import load_scenario

    b = bench or BenchConfig.from_options(**(options or {}), model=model)
    scenario = load_scenario(arg)
    src = sensor_source(scenario, model, bench=b)
    contact = scenario_contact(scenario)
    return OpenedSource(src, bool(getattr(src, "live", False)), b, getattr(src, "tare", None), (),
                        {"bench": b.to_meta(), "scenario_contact": contact["contact"],
                         **({"scenario_contacts": contact["contacts"]} if "contacts" in contact else {})})


def _synthetic(arg: str, *, rate_Hz=77.0, duration_s=None, model=None, **_) -> OpenedSource:
    from softphantom.viz.live.source import SyntheticSource

    if arg:
        raise UserError(f"--source synthetic:{arg}: synthetic takes no argument")
    _check_synthetic_model(model)
    return OpenedSource(SyntheticSource(rate_Hz=rate_Hz, duration_s=duration_s), True, None, None, (), {},
                        gives="estimates")


def _check_synthetic_model(model) -> None:
    """The synthetic source makes up the BIP's estimates (its four arms, its urethra, its targets):
    a model of other names is refused in one line rather than shown under the BIP's."""
    if model is None:
        return
    from softphantom.design import load_design
    from softphantom.design.params import BIPDesign

    design = getattr(model, "design", None)
    if design is None:
        path = Path(model) / "design.toml"
        if not path.is_file():
            return  # the model's own reader names what is missing where it is used
        design = load_design(path)
    bip = BIPDesign()
    mine = (design.sensing_names, design.pressure_names, tuple(design.target_dict))
    if mine != (bip.sensing_names, bip.pressure_names, tuple(bip.target_dict)):
        raise UserError(f"--source synthetic: made-up estimates of the BIP (arms {', '.join(bip.sensing_names)}; "
                        f"the urethra); this model has {', '.join(design.sensing_names)}"
                        f"{'; ' + ', '.join(design.pressure_names) if design.pressure_names else ''}: "
                        "use --source virtual:SCENARIO to see it")


def replay_holds(path: str | Path) -> str | None:
    """What a file for ``replay:`` holds, from its first bytes: ``measurements`` (a sensing
    recording), ``estimates`` (a session recording, an estimate file) or None (neither)."""
    from softphantom.sensing.recording import KIND

    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError:
        return None
    if head.startswith(b"\x89MCAP"):
        return "estimates"
    lines = head.decode("utf-8", "replace").lstrip("\ufeff").splitlines()
    meta: Any = {}
    if lines and lines[0].startswith("#"):
        try:
            meta = json.loads(lines[0][1:])
        except ValueError:
            return None
        lines = lines[1:]
    if isinstance(meta, dict) and meta.get("kind") == KIND:
        return "measurements"
    header = lines[0].split(",") if lines else []
    return "estimates" if "t_s" in header and "force_y_N" in header else None


def _replay(arg: str, *, model=None, bench=None, options=None, want=None, speed=1.0, **_) -> OpenedSource:
    if not Path(arg).is_file():
        raise UserError(f"--source replay:{arg}: replay file not found (no such file)")
    holds = replay_holds(arg) or want or "estimates"  # neither: its reader says what is wrong
    if holds == "measurements":
        return open_replay(arg, _model(model), bench, options=options)
    if want == "measurements":
        raise UserError(f"--source replay:{arg}: holds estimates (a session recording or an estimate file), not "
                        "sensor samples; estimate from a sensing recording (softphantom acquire --out)")
    from softphantom.viz.live.source import EstimateReplay

    model_dir = model if isinstance(model, (str, Path)) else None  # where the model's atlases are
    return OpenedSource(EstimateReplay(arg, speed=speed, model=_model(model), model_dir=model_dir), False, None,
                        None, (), {}, gives="estimates")


def _model(model):
    """A PhantomModel, or a model directory loaded (only the sources that need one ask)."""
    if model is None or not isinstance(model, (str, Path)):
        return model
    from softphantom.design import load_model

    return load_model(Path(model))


SOURCES: dict[str, SourceKind] = {k.scheme: k for k in (
    SourceKind("serial", "serial:PORT", "measurements", "the sensing board on a serial port or pyserial URL", _serial),
    SourceKind("replay", "replay:FILE", "recorded", "a sensing recording (samples), a session recording or an "
               "estimate file (estimates)", _replay),
    SourceKind("virtual", "virtual:SCENARIO", "measurements", "the virtual phantom running a scenario", _virtual),
    SourceKind("synthetic", "synthetic", "estimates", "made-up estimates for trying the live view", _synthetic),
)}


def usage() -> str:
    """``serial:PORT, replay:FILE, virtual:SCENARIO or synthetic``."""
    names = [k.usage for k in SOURCES.values()]
    return ", ".join(names[:-1]) + " or " + names[-1]


def open_source(spec: str, model=None, bench=None, *, want: str | None = None, **settings) -> OpenedSource:
    """Open ``--source`` ``spec`` (see the module docstring). ``model``: a PhantomModel or a model
    directory (the bench's default, the replay's geometry); ``bench``: a
    :class:`~softphantom.sensing.bench.BenchConfig` to use instead of the recorded/default one;
    ``want="measurements"`` refuses a source of estimates in one line. ``settings`` go to the
    kind that uses them: ``options`` (CLI bench options), ``tare_s``, ``on_new_board``,
    ``connect_timeout_s``, ``baud``, ``osr``, ``serial_opener`` (serial); ``speed`` (replay of
    estimates); ``rate_Hz``, ``duration_s`` (synthetic)."""
    scheme, colon, arg = spec.partition(":")
    kind = SOURCES.get(scheme)
    if kind is None:
        raise UserError(f"unknown --source {spec!r} (unknown kind {scheme!r}); use {usage()}")
    if kind.scheme != "synthetic" and not arg:
        raise UserError(f"--source {spec!r}: use {kind.usage}")
    if want == "measurements" and kind.gives == "estimates":
        raise UserError(f"--source {spec}: gives estimates, not sensor samples; use "
                        + ", ".join(k.usage for k in SOURCES.values() if k.gives != "estimates"))
    return kind.open(arg, model=model, bench=bench, want=want, **settings)
