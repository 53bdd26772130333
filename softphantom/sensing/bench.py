"""The bench in one place: tubing, cavities and ambient (:class:`BenchConfig`) → the sensor chain,
opening a board or a recording (:func:`open_serial`, :func:`open_replay`; the ``--source``
registry is :mod:`softphantom.sources`) and taring it at rest (:func:`tare_at_rest`), and
what to do when a new board appears mid-run (:class:`RetareSource`).

``acquire``, ``estimate``, ``live`` and the virtual phantom all take their chain from a
:class:`BenchConfig`; every recording stores it (``meta["bench"]``), so a replay converts pressure
to volume the way the trial did without any option.

>>> b = BenchConfig()
>>> [round(v * 1e9) for v in b.chain().v_total_m3], b.to_meta()["tube_id_mm"]
([14086, 14086, 14058, 14058], 1.2)
>>> BenchConfig.from_meta({"bench": b.to_meta()}).same_as(b)
True
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from softphantom.errors import UserError
from softphantom.records.channels import BIP_LAYOUT, ChannelLayout, ChannelNames, read_layout
from softphantom.records.names import SCENARIO_CLOCK
from softphantom.sensing.chain import SensorChain, Tare, default_chain, nominal_tare, tare_from_window
from softphantom.sensing.pneumatics import tube_volume_m3
from softphantom.sensing.measurement import (
    ARM_CAVITY_VOLUMES_M3,
    P0_STANDARD_PA,
    TUBE_ID_M,
    TUBE_LENGTH_M,
    Measurement,
)
from softphantom.sensing.sources import SensorSource, SourceEvent, SourceStats


NEW_BOARD_POLICIES = ("stop", "retare")
"""What a run does when the board restarts or is replaced (a ``restart`` event): ``stop`` ends it
with a one-line error (the default: a new board's zero is unknown), ``retare`` takes a new tare
from the next ``tare_s`` of frames, which must be at rest."""


def _positive(name: str, v: float) -> float:
    v = float(v)
    if not math.isfinite(v) or v <= 0:
        raise UserError(f"{name}: must be a positive number, got {v!r}")
    return v


@dataclass(frozen=True)
class BenchConfig(ChannelNames):
    """The pneumatic bench (SI): per-channel tube ``tube_length_m`` × ``tube_id_m`` (inner diameter),
    the volume channels' cavities ``cavity_volumes_m3`` (one per volume channel of ``layout``, its
    ``sensing``: the arms, then a design's measured internal cavities, each read as an arm is; the
    BIP's four arms by default), the transducers' extra dead volume ``v_dead_m3`` and the absolute
    ambient pressure ``p0_Pa`` at tare; as calibrated (``softphantom calibrate``, the design's
    ``[sensors]``): the volume transducers' ``gains`` (sensitivity / datasheet) and the
    ``tube_volume_factor`` (real / nominal tube volume); ``layout`` the board's
    :class:`~softphantom.records.channels.ChannelLayout` (default: the BIP's), its actuated cavities
    one pressure transducer (MPX4250D) each on the channels after the volume channels. The metadata
    (:meth:`to_meta`) keeps the name ``arm_cavity_mm3`` for the volume channels, measured cavities
    included; the layout is the recording's own (its ``channels``)."""

    tube_length_m: float = TUBE_LENGTH_M
    tube_id_m: float = TUBE_ID_M
    cavity_volumes_m3: tuple[float, ...] = ARM_CAVITY_VOLUMES_M3
    p0_Pa: float = P0_STANDARD_PA
    v_dead_m3: float = 0.0
    gains: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0)
    tube_volume_factor: float = 1.0
    layout: ChannelLayout = BIP_LAYOUT
    #: calibrated tube time constants (s), one per volume channel (empty: from the tube's length, bore
    #: and cavities; the lag compensation, :mod:`softphantom.estimation.lag`)
    tube_tau_s: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        _positive("--tube-length-m", self.tube_length_m)
        _positive("--tube-id-mm", self.tube_id_m * 1e3)
        _positive("--p0-kPa", self.p0_Pa / 1e3)
        n = len(self.layout.sensing)
        vc = tuple(float(v) for v in self.cavity_volumes_m3)
        if len(vc) != n or not all(math.isfinite(v) and v > 0 for v in vc):
            raise UserError(f"cavity volumes (mm³): expected {n} positive values, got {self.cavity_volumes_m3!r}")
        if not (math.isfinite(self.v_dead_m3) and self.v_dead_m3 >= 0):
            raise UserError(f"dead volume (mm³): must be ≥ 0, got {self.v_dead_m3 * 1e9!r}")
        object.__setattr__(self, "cavity_volumes_m3", vc)
        g = tuple(float(v) for v in self.gains)
        if len(g) != n or not all(math.isfinite(v) and v > 0 for v in g):
            raise UserError(f"transducer gains: expected {n} positive values, got {self.gains!r}")
        object.__setattr__(self, "gains", g)
        _positive("tube volume factor", self.tube_volume_factor)
        tt = tuple(float(v) for v in self.tube_tau_s)
        if tt and (len(tt) != n or not all(math.isfinite(v) and v > 0 for v in tt)):
            raise UserError(f"tube time constants (ms): expected {n} positive values, got "
                            f"{[v * 1e3 for v in tt]!r}")
        object.__setattr__(self, "tube_tau_s", tt)

    @classmethod
    def from_model(cls, model, **kw) -> "BenchConfig":
        """The bench of a :class:`~softphantom.design.PhantomModel`: its design's volume channels
        (its layout's ``sensing``: the arms, then the measured internal cavities) at their nominal
        volumes, and its actuated cavities' pressure channels; ``kw`` (``tube_length_m``,
        ``tube_id_m``, ``p0_Pa``; None = default) the rest."""
        d = model.design
        vc = tuple(v * 1e-9 for v in d.sensing_volumes_mm3())
        sensors = getattr(d, "sensors", None)
        cal = {} if sensors is None else {"gains": sensors.gains, "tube_volume_factor": sensors.tube_volume_factor,
                                          "tube_tau_s": tuple(v * 1e-3 for v in getattr(sensors, "tube_tau_ms", ()))}
        return cls(cavity_volumes_m3=vc, **cal, layout=d.channel_layout,
                   **{k: v for k, v in kw.items() if v is not None})

    @classmethod
    def from_options(cls, tube_length_m: float | None = None, tube_id_mm: float | None = None,
                     p0_kPa: float | None = None, model=None, base: "BenchConfig | None" = None) -> "BenchConfig":
        """From the CLI's units (``--tube-length-m``, ``--tube-id-mm``, ``--p0-kPa``; None keeps
        ``base``'s value, or the model's / the paper's)."""
        b = base or (cls.from_model(model) if model is not None else cls())
        kw = {}
        if tube_length_m is not None:
            kw["tube_length_m"] = tube_length_m
        if tube_id_mm is not None:
            kw["tube_id_m"] = _positive("--tube-id-mm", tube_id_mm) * 1e-3
        if p0_kPa is not None:
            kw["p0_Pa"] = _positive("--p0-kPa", p0_kPa) * 1e3
        return replace(b, **kw)

    def same_as(self, other: "BenchConfig | None", rtol: float = 1e-9) -> bool:
        """Equal up to rounding (metadata stores user units)."""
        if other is None:
            return False
        a = np.array([self.tube_length_m, self.tube_id_m, *self.cavity_volumes_m3, self.p0_Pa, self.v_dead_m3,
                      *self.gains, self.tube_volume_factor])
        b = np.array([other.tube_length_m, other.tube_id_m, *other.cavity_volumes_m3, other.p0_Pa, other.v_dead_m3,
                      *other.gains, other.tube_volume_factor])
        return bool(np.allclose(a, b, rtol=rtol, atol=0.0))

    def chain(self) -> SensorChain:
        """The sensor chain: V_total = cavity + factor × tube + dead volume per arm; each arm
        transducer's sensitivity × its gain."""
        base = default_chain(self.cavity_volumes_m3, self.tube_length_m, self.tube_id_m, self.v_dead_m3,
                             layout=self.layout)
        n = len(self.arm_names)
        if self.gains == (1.0,) * n and self.tube_volume_factor == 1.0:
            return base
        tube = tube_volume_m3(self.tube_length_m, self.tube_id_m)
        v = np.asarray(self.cavity_volumes_m3) + self.tube_volume_factor * tube + self.v_dead_m3
        tr = tuple(replace(t, k1_per_kPa=t.k1_per_kPa * g) for t, g in zip(base.transducers[:n], self.gains))
        return SensorChain(v, self.layout, tr + base.transducers[n:], base.bits)

    def describe(self) -> str:
        """One line for messages.

        >>> BenchConfig().describe()
        'tube 12 m × 1.2 mm, arm cavities 514/514/486/486 mm³'
        """
        cav = "/".join(f"{v * 1e9:.4g}" for v in self.cavity_volumes_m3)
        return f"tube {self.tube_length_m:g} m × {self.tube_id_m * 1e3:g} mm, arm cavities {cav} mm³"

    def to_meta(self) -> dict:
        """The recording metadata ``bench`` entry (user units; the channels' names are the file's
        layout, :data:`~softphantom.records.channels.LAYOUT_KEY`)."""
        out = {"tube_length_m": self.tube_length_m, "tube_id_mm": round(self.tube_id_m * 1e3, 9),
               "arm_cavity_mm3": [round(v * 1e9, 6) for v in self.cavity_volumes_m3],
               "p0_Pa": self.p0_Pa, "dead_volume_mm3": round(self.v_dead_m3 * 1e9, 6),
               "transducer_gains": list(self.gains), "tube_volume_factor": self.tube_volume_factor}
        if self.tube_tau_s:
            out["tube_tau_ms"] = [round(v * 1e3, 6) for v in self.tube_tau_s]
        return out

    @classmethod
    def from_meta(cls, meta: dict) -> "BenchConfig":
        """The bench of a recording: ``meta["bench"]`` (or the older ``design`` + ``p0_Pa`` keys)
        with the recording's layout (``meta["channels"]``; an older file's: the names its bench
        gave, :func:`~softphantom.records.channels.read_layout`)."""
        from softphantom.errors import FileFormatError

        b = meta.get("bench") or meta.get("design")
        try:
            layout = read_layout(meta, sensing=b.get("arm_names"), actuated=b.get("cavity_names"))
            return cls(float(b["tube_length_m"]), float(b["tube_id_mm"]) * 1e-3,
                       tuple(float(v) * 1e-9 for v in b["arm_cavity_mm3"]),
                       float(b.get("p0_Pa", meta.get("p0_Pa", P0_STANDARD_PA))),
                       float(b.get("dead_volume_mm3", 0.0)) * 1e-9,
                       tuple(float(v) for v in b.get("transducer_gains", (1.0,) * len(layout.sensing))),
                       float(b.get("tube_volume_factor", 1.0)), layout,
                       tuple(float(v) * 1e-3 for v in b.get("tube_tau_ms", ())))
        except KeyError as exc:
            has = ", ".join(map(str, b)) or "nothing"
            raise FileFormatError(f"metadata: no usable bench: no {exc} (it has {has})") from None
        except (TypeError, ValueError) as exc:
            raise FileFormatError(f"metadata: no usable bench (tube, cavities): {exc}") from None


def check_link_options(tare_s: float, connect_timeout_s: float, on_new_board: str) -> None:
    """The board options' values, checked before anything is opened (one-line errors naming the option).

    >>> check_link_options(-1, 5.0, "stop")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --tare-s: must be ≥ 0 (0: the datasheet zero), got -1.0
    """
    if not (math.isfinite(float(tare_s)) and tare_s >= 0):
        raise UserError(f"--tare-s: must be ≥ 0 (0: the datasheet zero), got {float(tare_s)!r}")
    _positive("--connect-timeout-s", connect_timeout_s)
    if on_new_board not in NEW_BOARD_POLICIES:
        raise UserError(f"--on-new-board: expected {' or '.join(NEW_BOARD_POLICIES)}, got {on_new_board!r}")


def tare_from_measurements(window: list[Measurement], bench: BenchConfig, chain: SensorChain | None = None) -> Tare:
    """:func:`~softphantom.sensing.chain.tare_from_window` over measurements (their raw sums)."""
    return tare_from_window(np.array([m.raw for m in window]), np.array([m.osr for m in window]),
                            np.array([m.t for m in window]), chain or bench.chain(), bench.p0_Pa)


def tare_at_rest(source: SensorSource, bench: BenchConfig, tare_s: float, *, label: str,
                 connect_timeout_s: float = 5.0, on_read: Callable[[list[Measurement]], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> tuple[Tare, list[Measurement]]:
    """Read ``source`` until ``tare_s`` of frames (≥ 5) arrived and tare on them (refused if not at
    rest). ``tare_s`` 0: the datasheet zero after the first frame. Returns the tare and the window
    (its measurements still carry the source's previous tare). ``label`` names the source in the
    one-line errors."""
    window: list[Measurement] = []
    t0 = clock()
    need = max(0.0, float(tare_s))
    while True:
        batch = source.read(0.05) or []
        window += batch
        if on_read is not None:
            on_read(batch)
        now = clock()
        if window and window[-1].t - window[0].t >= need and (need == 0 or len(window) >= 5):
            break
        if not window and now - t0 > connect_timeout_s:
            raise UserError(f"{label}: no valid frame within {connect_timeout_s:g} s (state "
                            f"{source.stats().state}; check the cable, --baud, the firmware)")
        if now - t0 > connect_timeout_s + need + 5:
            raise UserError(f"{label}: too few frames for a {need:g} s tare window")
    chain = getattr(source, "chain", None) or bench.chain()
    tare = nominal_tare(chain, bench.p0_Pa) if need == 0 else tare_from_measurements(window, bench, chain)
    return tare, window


class NewBoardError(UserError):
    """A board restarted or was replaced mid-run and the policy is ``stop``."""


class RetareSource(SensorSource):
    """A tared serial source with the new-board policy (:data:`NEW_BOARD_POLICIES`): after a
    ``restart`` event, ``stop`` raises :class:`NewBoardError` from :meth:`read` (the consumer ends
    the run cleanly, with the event recorded), ``retare`` holds the next ``tare_s`` of frames back,
    tares on them, emits a ``retared`` event and hands them on converted with the new tare —
    nothing is dropped. Everything else passes through."""

    live = True

    def __init__(self, source, bench: BenchConfig, policy: str = "stop", tare_s: float = 1.0, label: str = "board"):
        if policy not in NEW_BOARD_POLICIES:
            raise UserError(f"--on-new-board: expected {' or '.join(NEW_BOARD_POLICIES)}, got {policy!r}")
        self.inner, self.bench, self.policy, self.tare_s, self.label = source, bench, policy, tare_s, label
        self.chain = source.chain
        self._held: list[Measurement] | None = None
        self._held_events: list[SourceEvent] = []
        self._error: NewBoardError | None = None
        self._events: collections.deque[SourceEvent] = collections.deque()

    @property
    def tare(self) -> Tare:
        return self.inner.tare

    def read(self, timeout_s: float = 0.1) -> list[Measurement] | None:
        from softphantom.sensing.chain import to_measurement

        if self._error is not None:
            raise self._error
        batch = self.inner.read(timeout_s)
        restart = None
        for ev in self.inner.events():
            if ev.kind == "restart":
                restart = ev
            # while the frames are held back for the tare, so are the events from the restart on: they
            # come out with the frames, so that a recorder places each before the frame that follows it
            hold = self._held is not None or (restart is not None and self.policy == "retare")
            (self._held_events if hold else self._events).append(ev)
        before: list[Measurement] = []
        if restart is not None:
            # the policy applies whatever came with the event: a new board may announce itself by
            # an INFO frame alone, and then every frame that follows is its own
            frames = batch or []
            cut = self._new_board_at(frames)
            before, frames = frames[:cut], frames[cut:]
            if self.policy == "stop":
                self._error = NewBoardError(
                    f"{self.label}: the board restarted or was replaced at t = {restart.t:.3f} s (its zero is "
                    f"unknown); stopped — use --on-new-board retare to re-tare at rest and go on")
                if not before:
                    raise self._error
                return before
            self._held = []
            batch = frames if batch is not None else None
        if batch is None and self._held_events:  # the source ended during the tare window
            self._events.extend(self._held_events)
            self._held_events = []
        if batch is None or self._held is None:
            return batch if not before else before + (batch or [])
        self._held += batch
        # the window's length by the board clock (the host clock of a burst read at once is estimated)
        if not self._held or self._held[-1].t_board - self._held[0].t_board < self.tare_s or len(self._held) < 5:
            return before
        tare = tare_from_measurements(self._held, self.bench, self.chain)
        self.inner.set_tare(tare)
        # the new board began at its first frame at the latest (a burst read at once may be dated earlier
        # than the read that noticed the restart)
        self._events.extend(replace(e, t=min(e.t, self._held[0].t)) for e in self._held_events)
        self._events.append(SourceEvent(self._held[0].t, "retared",
                                        f"{tare.n_samples} frames at rest, {self.tare_s:g} s"))
        self._held_events = []
        out = [to_measurement(m.t, m.seq, m.t_board, m.raw, m.osr, self.chain, tare) for m in self._held]
        self._held = None
        return before + out

    def _new_board_at(self, frames: list[Measurement]) -> int:
        """Where the new board's frames start in ``frames`` (the read that brought the restart):
        as the serial source saw it (``new_board_at``), else where the board clock runs backwards."""
        at = getattr(self.inner, "new_board_at", None)
        if at is not None:
            return min(int(at), len(frames))
        return next((i for i in range(len(frames) - 1, 0, -1) if frames[i].t_board < frames[i - 1].t_board), 0)

    def stats(self) -> SourceStats:
        return self.inner.stats()

    def close(self) -> None:
        self.inner.close()


@dataclass(frozen=True)
class OpenedSource:
    """What :func:`softphantom.sources.open_source` gives: the ``source``, ``live`` (a board:
    estimate the newest samples, never wait for it), the ``bench`` its volumes follow, the ``tare``
    in force, the rest ``window`` it was tared on (serial), ``meta`` to store with any output,
    ``notes`` (one line each) the user should read, e.g. a recording's bench that could not be
    used, and what it ``gives``: ``measurements`` (a :class:`SensorSource`) or ``estimates`` (an
    estimate source of the live view)."""

    source: SensorSource
    live: bool
    bench: BenchConfig | None
    tare: Tare | None
    window: tuple[Measurement, ...]
    meta: dict
    notes: tuple[str, ...] = ()
    gives: str = "measurements"


def open_replay(path: str, model=None, bench: BenchConfig | None = None, *, options: dict | None = None) -> OpenedSource:
    """A sensing recording replayed: its own bench and tare; a bench that differs (``bench``, or the
    CLI ``options`` ``tube_length_m``, ``tube_id_mm``, ``p0_kPa``; None = keep) re-converts the raw
    sums. (``--source replay:FILE`` of a sensing recording: :func:`softphantom.sources.open_source`.)"""
    from softphantom.sensing.recording import read_recording
    from softphantom.sensing.sources import ReplaySource

    options = options or {}
    arg = path
    if not Path(arg).is_file():
        raise UserError(f"--source replay:{arg}: no such file")
    rec = read_recording(arg)
    meta = rec.meta
    if model is not None:
        mine, theirs = rec.layout.channels, model.layout.channels
        if (rec.layout.sensing, rec.layout.actuated) != (model.layout.sensing, model.layout.actuated):
            raise UserError(f"--source replay:{arg}: its channels ({', '.join(mine)}) are not the model's "
                            f"({', '.join(theirs)})")
    recorded = base = None
    notes: tuple[str, ...] = ()
    if "bench" in meta or "design" in meta:
        try:
            recorded = base = BenchConfig.from_meta(meta)
        except UserError as exc:  # another program's or version's shape: the raw sums still hold
            base = BenchConfig.from_model(model) if model is not None else BenchConfig()
            why = str(exc).removeprefix("metadata: ")
    use = bench or (BenchConfig.from_options(**options, base=base) if base or any(
        v is not None for v in options.values()) else None)
    if base is not None and recorded is None:
        whose = "given" if bench is not None else "design's" if model is not None else "paper's"
        notes = (f"replay:{arg}: {why}; using the {whose} bench ({use.describe()}), the volumes re-converted "
                 "from the raw sums",)
    reconvert = use is not None and not use.same_as(recorded)
    given = {"tube_length_m": options.get("tube_length_m"), "tube_id_mm": options.get("tube_id_mm")}
    stored = meta.get("bench") or meta.get("design") or {}
    stored = stored if isinstance(stored, dict) else {}
    tube_missing = next((k for k, v in given.items() if v is None and k not in stored), None) if bench is None else None
    src = ReplaySource(arg, chain=use.chain() if reconvert else None,
                       tare=_retared_p0(meta, use) if reconvert else None)
    return OpenedSource(src, False, use or BenchConfig(), None, (),
                        {"bench": (use or BenchConfig()).to_meta(), "reconverted": reconvert,
                         "recording_contact": meta.get("contact"),
                         **({"recording_contacts": meta["contacts"]} if meta.get("contacts") else {}), **({"bench_note": notes[0]} if notes else {}),
                         **({"tube_missing": tube_missing} if tube_missing else {}),
                         **({"clock": SCENARIO_CLOCK} if meta.get("virtual") else {})},
                        notes)


def open_serial(port: str, model=None, bench: BenchConfig | None = None, *, options: dict | None = None,
                tare_s: float = 1.0, on_new_board: str = "stop", connect_timeout_s: float = 5.0,
                baud: int = 115_200, osr: int | None = None, serial_opener: Callable | None = None) -> OpenedSource:
    """The board on ``port``, tared on its first ``tare_s`` at rest, then the new-board policy. The
    bench: ``bench``, else the model's design / the paper's, with the CLI ``options`` applied.
    (``--source serial:PORT``: :func:`softphantom.sources.open_source`.)"""
    from softphantom.sensing.sources import SerialSource

    check_link_options(tare_s, connect_timeout_s, on_new_board)
    b = bench or BenchConfig.from_options(**(options or {}), model=model)
    chain = b.chain()
    kw = {"opener": serial_opener} if serial_opener is not None else {}
    src = SerialSource(port, chain, nominal_tare(chain, b.p0_Pa), baud=baud, osr=osr, **kw)
    try:
        tare, window = tare_at_rest(src, b, tare_s, label=f"--source serial:{port}",
                                    connect_timeout_s=connect_timeout_s)
    except BaseException:
        src.close()
        raise
    src.set_tare(tare)
    src.events()                            # connecting is not an outage
    st = src.stats()
    meta = {"bench": b.to_meta(), "tare": tare.to_dict(), "firmware": st.firmware, "osr": st.osr,
            "protocol_version": st.decoder.version, "on_new_board": on_new_board}
    return OpenedSource(RetareSource(src, b, on_new_board, tare_s, f"--source serial:{port}"), True, b,
                        tare, tuple(window), meta)


def _retared_p0(meta: dict, bench: BenchConfig) -> Tare:
    """The recording's tare with the ambient pressure of ``bench`` (the offsets are the board's)."""
    from softphantom.errors import FileFormatError

    if "tare" not in meta:
        raise FileFormatError("recording metadata has no tare: cannot re-convert its raw sums")
    t = Tare.from_dict(meta["tare"])
    return Tare(t.offset_codes, bench.p0_Pa, t.n_samples, t.t_s, t.noise_Pa)
