"""What every command gets without asking: finite numbers, Ctrl-C → exit 130, one output policy.

:func:`harden` is applied once by :func:`softphantom.cli.main` to the whole command tree, so a
command added by any module gets it:

- every numeric option rejects NaN and ±inf (a usage error, exit 2, naming the option);
- every help text is shown as written: typer renders it as rich markup, which would take
  ``[molds]`` for a style tag and drop it, so the text is escaped once here;
- Ctrl-C inside a command prints ``interrupted`` on stderr and exits 130 (the shell convention,
  so ``make`` stops); commands whose normal stop is Ctrl-C (``acquire``, ``live``, …) close their
  recording first and end with :func:`stopped`, which also exits 130.

Outputs (``--out``): :func:`staged_output` refuses an existing file or non-empty directory unless
``--overwrite`` (:data:`Overwrite`), writes into a hidden sibling and moves the result into
place only when the command succeeds, so an error or Ctrl-C leaves no partial output and loses
nothing that was there before.

Options that several commands take are declared once, here, as ``Annotated`` aliases (flag and help
text); a command gives only the type's default, e.g. ``model_dir: ModelDir = ...`` (required) or
``seed: Seed = 0``. What one command does more with an option is said in its own description. A flag
that means different things in different commands is listed in :data:`FLAGS_OF_SEVERAL_MEANINGS`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import math
import os
import shutil
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, NoReturn, Optional, get_type_hints

import typer

from softphantom.errors import UserError

EXIT_INTERRUPTED = 130  # 128 + SIGINT


def finite_number(text: str, option: str) -> float:
    """``float(text)`` for an option parsed by hand (``--lag-ms``, ``X,Y,Z``): finite, else UserError.

    >>> finite_number("2.5", "--lag-ms")
    2.5
    >>> finite_number("nan", "--lag-ms")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --lag-ms: expected a finite number, got 'nan'
    """
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise UserError(f"{option}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise UserError(f"{option}: expected a finite number, got {text!r}")
    return v


def check_choice(value: str, choices: tuple[str, ...] | list[str], option: str) -> str:
    """``value`` if it is one of ``choices``, else a UserError naming ``option`` and the choices.

    >>> check_choice("furlong", ("m", "cm", "mm"), "--length-unit")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --length-unit: expected m, cm or mm, got 'furlong'
    """
    if value not in choices:
        words = ", ".join(choices[:-1]) + f" or {choices[-1]}" if len(choices) > 1 else choices[0]
        raise UserError(f"{option}: expected {words}, got {value!r}")
    return value


def check_positive(value: float | None, option: str, unit: str = "", *, zero: bool = False) -> float | None:
    """``value`` (None passes) if > 0 (``zero``: >= 0), else a UserError naming ``option``.

    >>> check_positive(-1.0, "--connect-timeout-s", "s")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --connect-timeout-s: must be > 0 s, got -1
    """
    if value is not None and not (value >= 0 if zero else value > 0):
        raise UserError(f"{option}: must be {'>=' if zero else '>'} 0{' ' + unit if unit else ''}, got {value:g}")
    return value


# --- options shared by several commands -----------------------------------------------------------

ModelDir = Annotated[Optional[Path], typer.Option(
    "--model", help="Model directory (written by softphantom design, or calibrate).")]
Out = Annotated[Optional[Path], typer.Option(
    "--out", help="Where to write: the file or directory the command's description names (an existing one is "
    "refused, or replaced with --overwrite where the command has it).")]
Overwrite = Annotated[bool, typer.Option(
    "--overwrite", help="Replace an existing --out (a directory keeps the entries this command does not write).")]
At = Annotated[Optional[str], typer.Option(
    "--at", help="Contact point (the model's p_ext): on-centre, off-centre or one of the design's [contacts]. "
    "Where no default is shown: the recording's (replay), the scenario's (virtual), else on-centre.")]
Seed = Annotated[int, typer.Option(
    "--seed", help="Seed of every random draw (a virtual board's noise, offsets, drift, lost frames and clocks; "
    "atlas check's held-out loads and starts).")]
Osr = Annotated[Optional[int], typer.Option(
    "--osr", help="Oversampling: readings summed per channel per frame, 1..500 (on the BIP's 5-channel board "
    "100: 19.2 Hz, the paper's; 25: 76.9 Hz).")]
Scheduler = Annotated[Optional[str], typer.Option(
    "--scheduler", help="Address of a running Dask scheduler (tcp://HOST:PORT) for the solves; default: a "
    "local cluster.")]
Workers = Annotated[Optional[int], typer.Option(
    "--workers", help="Worker processes of the local cluster (default: all cores).")]
DurationS = Annotated[Optional[float], typer.Option(
    "--duration-s", help="Stop after this many seconds (default: at the end of a replay or scenario, else "
    "Ctrl-C).")]
TubeLengthM = Annotated[Optional[float], typer.Option(
    "--tube-length-m", help="Tube length per channel (m). Where no default is shown: a replay's recorded one, "
    "else 12 m.")]
TubeIdMm = Annotated[Optional[float], typer.Option(
    "--tube-id-mm", help="Tube inner diameter (mm). Where no default is shown: a replay's recorded one, else "
    "1.2 mm.")]
P0KPa = Annotated[Optional[float], typer.Option(
    "--p0-kPa", help="Absolute ambient pressure at tare (kPa). Where no default is shown: a replay's recorded "
    "one, else 101.325.")]
TareS = Annotated[float, typer.Option(
    "--tare-s", help="Serial: the rest window at the start the sensors are tared on (s).")]
OnNewBoard = Annotated[str, typer.Option(
    "--on-new-board", help="Serial: when the board restarts or is replaced mid-run: stop (one-line error, the "
    "run so far is kept) | retare (re-tare on the next rest window and go on).")]
LagCompensation = Annotated[Optional[str], typer.Option(
    "--lag-compensation", help="The tubes' pneumatic lag: model (estimate the cavity pressures of now from a "
    "model of each tube, docs/estimation.md) | off. Default: model where the tubes' time constant exceeds 10 ms "
    "(the paper's 12 m tubes: 0.1 s).")]
MaxForceN = Annotated[float, typer.Option(
    "--max-force-N", help="Estimated sources: bound on each force component (N).")]
Estimator = Annotated[Optional[str], typer.Option(
    "--estimator", help="Estimated sources: atlas (precomputed equilibria, real time; built once per model and "
    "cached in MODEL/atlas/; a stack of atlases over further cavities' pressures) | refresh (the linearization "
    "refreshed per sample; needs no atlas, takes a design without an actuated internal cavity).")]
AtlasGrid = Annotated[Optional[str], typer.Option(
    "--atlas-grid", help="Atlas to build: Chebyshev points per axis NX,NY,NZ,NP (default: the model's, "
    "default_atlas_config: 11,9,4,3 with f_x stretched about 0 N on a linear model; 11,6,5,3 per piece, "
    "Hermite along f_z, on a quadratic one).")]
AtlasXAxis = Annotated[Optional[str], typer.Option(
    "--atlas-x-axis", help="Atlas: the first axis, force (f_x; the default on a linear model) | displacement "
    "(the contact patch's x-displacement mapped onto the f_x range, f_x an output: for a model whose state "
    "nearly jumps in f_x, docs/estimation.md; the default on a quadratic model).")]
AtlasFYSplitN = Annotated[Optional[str], typer.Option(
    "--atlas-f-y-split-N", help="Atlas: build it in pieces along f_y, split at these forces (N, comma-separated), "
    "each piece with the grid of --atlas-grid: for a model whose map bends sharply at one f_y (the quadratic "
    "model's fold above ≈ 4.3 N, docs/estimation.md; its default 3.3; '' for one piece).")]
Envelope = Annotated[Optional[str], typer.Option(
    "--envelope", help="Atlas: load envelope FXMIN:FXMAX,FYMIN:FYMAX,FZMIN:FZMAX,PMIN:PMAX in N and kPa "
    "(default -2:2,-1:5.2,-2:2,-2:40); outside it an estimate is clamped and flagged (in_envelope 0).")]
DraftAtlas = Annotated[bool, typer.Option(
    "--draft", help="Where the model has no full atlas for a contact and none is shipped: build its draft atlas "
    "(atlas build --draft: a coarse grid, its held-out error measured and printed) and use it, instead of "
    "refusing a build that takes hours.")]
Scenario = Annotated[str, typer.Option(
    "--scenario", help="Scenario TOML file, or a bundled one: needle-insertion, push-on-centre, "
    "push-off-centre, urethra-inflation.")]
TruthMeshScale = Annotated[float, typer.Option(
    "--truth-mesh-scale", help="The virtual truth's node spacing relative to the estimator model's mesh size "
    "(< 1: finer; P2 elements are twice that).")]
TruthOrder = Annotated[int, typer.Option(
    "--truth-order", help="The virtual truth's element order: 2 (10-node tets) or 1.")]
Board = Annotated[str, typer.Option(
    "--board", help="The virtual board: python (a model of the firmware) or firmware (firmware/main.c run in "
    "simavr; needs the Debian packages simavr, libsimavr-dev).")]
Mcu = Annotated[str, typer.Option(
    "--mcu", help="With --board firmware, the Arduino the firmware is built for and emulated on: uno "
    "(ATmega328P, 6 analog inputs: the arms and the internal cavities, e.g. 5 arms and the urethra) or mega "
    "(ATmega2560, 16 analog inputs).")]
Source = Annotated[Optional[str], typer.Option(
    "--source", help="Where the samples come from: serial:PORT | replay:FILE (a sensing recording, estimated; "
    "live also replays a session .mcap or an estimate .csv) | virtual:SCENARIO | synthetic (live).")]
Speed = Annotated[float, typer.Option(
    "--speed", help="Playback speed factor (1: real time; live also takes 0: as fast as possible).")]
AllowRemote = Annotated[bool, typer.Option(
    "--allow-remote", help="Serve beyond loopback (the command's host option may then name any interface); "
    "the data streams have no authentication (live's page and --foxglove require a token, printed in their "
    "addresses).")]
ConnectTimeoutS = Annotated[float, typer.Option(
    "--connect-timeout-s", help="Give up when nothing answers within this time (s): no frame from the board "
    "(acquire), no tracker server (track).")]
Body = Annotated[Optional[str], typer.Option(
    "--body", help="Rigid body: its Motive name or NatNet id, or body/topic in a bag; may be left out when "
    "there is one.")]
Png = Annotated[bool, typer.Option("--png/--no-png", help="Draw the result as a PNG (mesh.png, assembly.png).")]
MeshSizeMm = Annotated[Optional[float], typer.Option(
    "--mesh-size-mm", help="Bulb element size in mm; arm and cavity sizes scale with it.")]
Force = Annotated[bool, typer.Option(
    "--force", help="Go past the mesh guards: mesh above the element-count limit (design also: keep cavity "
    "volumes beyond the tolerance and an unobservable arm layout; docs/robustness.md).")]
NatnetVersion = Annotated[Optional[str], typer.Option(
    "--natnet-version", help="NatNet version, 3.0 or 4.1: the one virtual serve speaks, or the one evaluate "
    "reads a capture without the server's info reply as.")]


@dataclasses.dataclass(frozen=True)
class TruthOptions:
    """The virtual truth's options (demo, virtual run, virtual serve): the draws' seed, the board's
    oversampling, the truth's mesh and element order."""

    seed: Seed = 0
    osr: Osr = 25
    truth_mesh_scale: TruthMeshScale = 0.75
    truth_order: TruthOrder = 2


@dataclasses.dataclass(frozen=True)
class VirtualOptions(TruthOptions):
    """:class:`TruthOptions` and the virtual board's (virtual run, virtual serve): its tubes (None:
    the paper's), its kind and the Arduino it emulates."""

    tube_length_m: TubeLengthM = None
    tube_id_mm: TubeIdMm = None
    board: Board = "python"
    mcu: Mcu = "uno"


def with_option_groups(command: Any) -> Any:
    """Let ``command`` take option groups: a parameter annotated with a dataclass of option aliases
    (``virtual: VirtualOptions = VirtualOptions(osr=100)``) stands, in the command line, for the
    group's fields in their order, each with the given instance's value as its default; the command
    is called with the instance they make. Apply below ``@app.command``."""
    hints = get_type_hints(command, include_extras=True)
    params: list[inspect.Parameter] = []
    groups: dict[str, tuple[type, tuple[str, ...]]] = {}
    for p in inspect.signature(command).parameters.values():
        cls = hints.get(p.name)
        if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
            params.append(p.replace(annotation=hints.get(p.name, p.annotation)))
            continue
        given = cls() if p.default is p.empty else p.default
        fields = get_type_hints(cls, include_extras=True)
        names = tuple(f.name for f in dataclasses.fields(cls))
        groups[p.name] = (cls, names)
        params += [inspect.Parameter(n, p.kind, annotation=fields[n], default=getattr(given, n)) for n in names]
    flat = [p.name for p in params]
    if len(set(flat)) != len(flat):
        raise TypeError(f"{command.__name__}: an option group's field has the name of another parameter")

    @functools.wraps(command)
    def run(**kwargs: Any) -> Any:
        for name, (cls, names) in groups.items():
            kwargs[name] = cls(**{n: kwargs.pop(n) for n in names})
        return command(**kwargs)

    run.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
    run.__annotations__ = {p.name: p.annotation for p in params}
    return run


FLAGS_OF_SEVERAL_MEANINGS = {
    "--config": "design: a design file; sweep: a sweep file",
    "--draft": "atlas build: build the draft atlas; demo and estimate: build and use it where no full atlas exists",
    "--max-force-N": "estimate and live: the estimate's bound; atlas check: a goal on its error",
    "--natnet": "track: the server's address; virtual serve: serve one",
    "--rest-window-s": "evaluate: START,END on the tracker clock; track: a length at the start",
    "--truth": "evaluate: the truth of one estimate file; calibrate: a tracker take per --recording",
}
"""Flags declared by more than one command with a help of each's own, because they are different
options (flag → what each means); every other flag has one declaration, above."""


def check_workers(workers: int | None, *, zero: bool = False) -> None:
    """Refuse ``--workers`` below 1 (``zero``: below 0, 0 meaning no cluster) before any work."""
    if workers is not None and workers < (0 if zero else 1):
        raise UserError(f"--workers must be >= {0 if zero else 1}, got {workers}")


# --- applied to the whole command tree ------------------------------------------------------------

def _check_finite(ctx: Any, param: Any, value: Any) -> None:
    items = value if isinstance(value, (list, tuple)) else (value,)
    for v in items:
        if isinstance(v, float) and not math.isfinite(v):
            raise typer.BadParameter(f"expected a finite number, got {v}", ctx=ctx, param=param)


def _finite_callback(callback: Any) -> Any:
    def cb(ctx: Any, param: Any, value: Any) -> Any:
        _check_finite(ctx, param, value)
        return callback(ctx, param, value) if callback is not None else value

    return cb


def _interruptible(fn: Any) -> Any:
    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except KeyboardInterrupt:
            from softphantom.cli.app import print_error

            print_error("interrupted", prefix="")
            raise typer.Exit(EXIT_INTERRUPTED) from None

    return run


def _literal(text: str | None) -> str | None:
    from rich.markup import escape

    return None if text is None else escape(text)


def harden(command: Any) -> Any:
    """Give every parameter of ``command`` (a click command or group, recursively) the finite-number
    check, every command callback the Ctrl-C → 130 handling and every help text its literal
    rendering (markup escaped). Returns ``command``."""
    if not getattr(command, "_softphantom_help_literal", False):
        command.help, command.short_help = _literal(command.help), _literal(command.short_help)
        command._softphantom_help_literal = True
    for p in getattr(command, "params", ()):
        if not getattr(p, "_softphantom_hardened", False):
            p.callback = _finite_callback(p.callback)
            if getattr(p, "help", None) is not None:
                p.help = _literal(p.help)
            p._softphantom_hardened = True
    cb = getattr(command, "callback", None)
    if cb is not None and not getattr(cb, "_softphantom_hardened", False):
        command.callback = _interruptible(cb)
        command.callback._softphantom_hardened = True
    for sub in getattr(command, "commands", {}).values():
        harden(sub)
    return command


def stopped(message: str = "stopped (Ctrl-C)") -> NoReturn:
    """End a command that Ctrl-C stops by design, after it has closed its outputs: exit 130."""
    from softphantom.cli.app import print_error

    print_error(message, prefix="")
    raise typer.Exit(EXIT_INTERRUPTED)


# --- outputs ------------------------------------------------------------------------------------

def check_output(path: Path, *, overwrite: bool, directory: bool, option: str = "--out") -> None:
    """Refuse an output that exists (a file, a non-empty directory) unless ``overwrite``, one that
    is of the other kind (a file for a directory), and a directory that holds the working one."""
    path = Path(path)
    if path.is_dir():
        if not directory:
            raise UserError(f"{option} {path}: is a directory (expected a file name)")
        if any(path.iterdir()) and not overwrite:
            raise UserError(f"{option} {path}: exists and is not empty; use --overwrite to replace its contents")
        if overwrite and Path.cwd().resolve().is_relative_to(path.resolve()):
            raise UserError(f"{option} {path}: holds the working directory; refusing to overwrite it")
    elif path.exists() or path.is_symlink():
        if directory:
            raise UserError(f"{option} {path}: exists and is not a directory")
        if not overwrite:
            raise UserError(f"{option} {path}: exists; use --overwrite to replace it")
    _check_parent(path, option)


def _check_parent(path: Path, option: str) -> None:
    """Refuse an output whose folder cannot be made (an existing file on its way) or written, before
    the command's work rather than at its end; missing folders are made when it is written."""
    parent = path.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise UserError(f"{option} {path}: cannot be created ({parent} is a file, not a directory)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"{option} {path}: cannot be created ({parent}: permission denied)")


@contextlib.contextmanager
def _no_sigint() -> Iterator[None]:
    """Hold Ctrl-C during a few renames (re-raised after), so the move into place is never half done."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    hit: list[bool] = []
    old = signal.signal(signal.SIGINT, lambda *_: hit.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
    if hit:
        raise KeyboardInterrupt


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def _commit(stage: Path, path: Path, directory: bool) -> None:
    with _no_sigint():
        if not directory or not path.is_dir():
            if path.exists() or path.is_symlink():
                _remove(path)  # --overwrite, checked before
            os.replace(stage, path)
            return
        # merge into an existing directory: each entry written replaces the one of that name
        aside = []
        for entry in sorted(stage.iterdir()):
            target = path / entry.name
            if target.exists() or target.is_symlink():
                old = stage.with_name(f"{stage.name}.old-{entry.name}")
                os.replace(target, old)
                aside.append(old)
            os.replace(entry, target)
        stage.rmdir()
    for old in aside:
        _remove(old)


@contextlib.contextmanager
def staged_output(path: Path, *, overwrite: bool, directory: bool, option: str = "--out") -> Iterator[Path]:
    """Yield a hidden working path next to ``path``; on success move it into place, on any error or
    Ctrl-C remove it (``path`` is then as it was). Checks ``path`` first (:func:`check_output`).

    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> with staged_output(d / "a.txt", overwrite=False, directory=False) as tmp:
    ...     _ = tmp.write_text("one")
    >>> (d / "a.txt").read_text(), sorted(p.name for p in d.iterdir())
    ('one', ['a.txt'])
    >>> with staged_output(d / "a.txt", overwrite=False, directory=False) as tmp:
    ...     pass
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --out ...a.txt: exists; use --overwrite to replace it
    """
    path = Path(path)
    check_output(path, overwrite=overwrite, directory=directory, option=option)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{option} {path}: cannot create {path.parent} ({exc.strerror})") from None
    stage = path.with_name(f".{path.name}.partial-{os.getpid()}")
    _remove(stage)
    if directory:
        try:
            stage.mkdir()
        except OSError as exc:
            raise UserError(f"{option} {path}: cannot write in {path.parent} ({exc.strerror})") from None
    try:
        yield stage
    except BaseException:
        _remove(stage)
        raise
    try:
        _commit(stage, path, directory)
    except BaseException:
        _remove(stage)
        raise
