"""A virtual-phantom run: truth → sensor frames (a :class:`SensorSource`) + tracker stream + files.

``simulate(scenario, model)`` solves the truth (see :mod:`softphantom.virtual.truth`) and prepares
the board and the tracker; ``sensor_source(scenario, model)`` gives the frames through the real
decoder (:class:`~softphantom.sensing.sources.FrameSource`), tared on the rest window at the start
exactly as ``softphantom acquire`` does; ``write_run`` writes the files of ``softphantom virtual
run``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from softphantom.design import PhantomModel
from softphantom.errors import UserError
from softphantom.sensing.bench import BenchConfig, tare_from_measurements
from softphantom.sensing.board import frame_rate_Hz
from softphantom.sensing.chain import SensorChain, Tare, nominal_tare
from softphantom.sensing.sources import FrameSource
from softphantom.virtual.board import FIRMWARE, BoardConfig, BoardSignals, VirtualBoard, arm_volumes, board_signals
from softphantom.virtual.scenario import Event, Scenario, load_scenario
from softphantom.virtual.tracker import TrackerConfig, TrackerStream, simulate_tracker, write_motive_csv
from softphantom.virtual.truth import Truth, TruthConfig, solve_truth, write_snapshot
from softphantom.records.names import POSE_COLUMNS

TRUTH_RATE_HZ = 120.0
CHUNK_S = 0.1
BOARD_KINDS = ("python", "firmware")
"""The virtual board: the Python model of the firmware, or the firmware itself run in simavr."""


@dataclass(frozen=True)
class VirtualConfig:
    """Everything a run needs besides the scenario and the model (all seeded by ``seed``
    unless a part's own seed is set)."""

    truth: TruthConfig = field(default_factory=TruthConfig)
    board: BoardConfig = field(default_factory=BoardConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    #: "python" (softphantom.virtual.board) or "firmware" (firmware/main.c in simavr)
    board_kind: str = "python"

    def __post_init__(self) -> None:
        if self.board_kind not in BOARD_KINDS:
            raise UserError(f"--board: must be one of {', '.join(BOARD_KINDS)}, got {self.board_kind!r}")

    @classmethod
    def seeded(cls, seed: int = 0, osr: int = 25, board_kind: str = "python", **truth_kw) -> "VirtualConfig":
        return cls(TruthConfig(**truth_kw), BoardConfig(osr=osr, seed=seed), TrackerConfig(seed=seed), board_kind)


@dataclass(frozen=True, eq=False)
class VirtualRun:
    """A simulated run: ``truth``, ``signals`` at the transducers, ``tracker`` stream, the host's
    ``chain`` (the design's nominal cavity volumes + tubes, as ``acquire`` assumes)."""

    scenario: Scenario
    model: PhantomModel
    truth: Truth
    signals: BoardSignals
    tracker: TrackerStream
    chain: SensorChain
    config: VirtualConfig

    def board(self):
        """A fresh virtual board (frames from the start, same seed): a
        :class:`~softphantom.virtual.board.VirtualBoard`, or with ``board_kind`` "firmware" a
        :class:`~softphantom.virtual.firmware_sim.FirmwareBoard` (needs simavr)."""
        if self.config.board_kind == "firmware":
            from softphantom.virtual.firmware_sim import FirmwareBoard

            return FirmwareBoard(self.signals, self.config.board)
        return VirtualBoard(self.signals, self.config.board)

    @property
    def rate_Hz(self) -> float:
        """The board's nominal frame rate at the configured OSR."""
        return frame_rate_Hz(self.config.board.osr, n_channels=self.chain.n_channels)

    @cached_property
    def _frame_bytes(self) -> bytes:
        b = self.board()
        info = b.info()
        data, _ = b.frames(self.scenario.duration_s)
        if hasattr(b, "close"):
            b.close()
        return info + data

    def frame_bytes(self) -> bytes:
        """All frames of the scenario as the board sends them: INFO, then DATA frames."""
        return self._frame_bytes

    def tare(self) -> Tare:
        """The tare from the rest window at the start (all frames before ``rest_s`` − 0.1 s)."""
        src = FrameSource([self.frame_bytes()], self.chain, nominal_tare(self.chain, self.config.board.p0_Pa))
        win = [m for m in src if m.t <= self.scenario.rest_s - 0.1]
        return tare_from_measurements(win, host_bench(self.model, self.config.board), self.chain)

    def source(self, tare: bool = True) -> FrameSource:
        """The frames through the decoder as a :class:`FrameSource` (chunks of 0.1 s; host time =
        board time = scenario time), tared on the rest window (or the datasheet zero)."""
        data = self.frame_bytes()
        rate = self.rate_Hz
        from softphantom.sensing.protocol import data_frame_bytes

        step = max(1, int(round(CHUNK_S * rate))) * data_frame_bytes(self.chain.n_channels)
        chunks = [data[i:i + step] for i in range(0, len(data), step)]
        t = self.tare() if tare else nominal_tare(self.chain, self.config.board.p0_Pa)
        return FrameSource(chunks, self.chain, t)

    def truth_columns(self, rate_Hz: float = TRUTH_RATE_HZ) -> dict[str, np.ndarray]:
        """The truth file's columns (docs/architecture.md) on the scenario clock at ``rate_Hz``."""
        t = np.arange(0.0, self.scenario.duration_s + 1e-9, 1.0 / rate_Hz)
        s = self.truth.sample(t)
        cols: dict[str, np.ndarray] = {"t_s": t}
        v = s.pose.to_mm_deg()
        for k, name in enumerate(POSE_COLUMNS):
            cols[name] = v[:, k]
        for k, a in enumerate("xyz"):
            cols[f"force_{a}_N"] = s.force[:, k]
        for j, c in enumerate(s.cavity_names):  # the actuated internal cavities (the BIP: p_urethra_kPa)
            cols[f"p_{c}_kPa"] = s.pressures[:, j] / 1e3
        for j, name in enumerate(self.truth.target_names):
            for k, a in enumerate("xyz"):
                cols[f"{name}_d{a}_mm"] = s.targets[:, j, k] * 1e3
        for i, c in enumerate(self.truth.model.design.cavity_names):  # the arms, then every internal cavity
            cols[f"dV_{c}_mm3"] = s.dV[:, i] * 1e9
        return cols


def host_bench(model: PhantomModel, board: BoardConfig = BoardConfig()) -> BenchConfig:
    """The bench the host assumes: the design's nominal volume-channel cavities behind the board's tubes."""
    return BenchConfig.from_model(model, tube_length_m=board.tube_length_m, tube_id_m=board.tube_id_m,
                                  p0_Pa=board.p0_Pa)


def host_chain(model: PhantomModel, board: BoardConfig = BoardConfig()) -> SensorChain:
    """The chain the host assumes (:func:`host_bench`)."""
    return host_bench(model, board).chain()


def simulate(scenario: Scenario | str | Path, model: PhantomModel, config: VirtualConfig = VirtualConfig(),
             truth: Truth | None = None, truth_mesh: PhantomModel | None = None, *, cache: bool = True) -> VirtualRun:
    """Solve the truth of ``scenario`` (unless ``truth`` is given; ``cache``: through the truth
    cache, :func:`~softphantom.virtual.truth.solve_truth`) and prepare board and tracker."""
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    chain = host_chain(model, config.board)  # before the solve: a design the board cannot read is refused now
    tr = truth or solve_truth(sc, model, config.truth, truth_mesh=truth_mesh, cache=cache)
    sig = board_signals(tr, arm_volumes(tr.model), config.board)
    trk = simulate_tracker(tr, config.tracker)
    return VirtualRun(sc, model, tr, sig, trk, chain, config)


def sensor_source(scenario: Scenario | str | Path, model: PhantomModel, config: VirtualConfig = VirtualConfig(),
                *, tare: bool = True,
                run: VirtualRun | None = None, bench: BenchConfig | None = None) -> FrameSource:
    """A :class:`~softphantom.sensing.sources.SensorSource` of the virtual phantom running
    ``scenario`` on ``model``: the firmware's frames through the real decoder, tared on the rest
    window at the start. ``bench`` (tubes, ambient) is the bench both the board's physics and the
    host use. Solves the truth first (seconds to minutes, its progress logged: :func:`simulate`)."""
    if bench is not None:
        config = replace(config, board=replace(config.board, tube_length_m=bench.tube_length_m,
                                               tube_id_m=bench.tube_id_m, p0_Pa=bench.p0_Pa))
    run = run or simulate(scenario, model, config)
    return run.source(tare=tare)


def write_run(run: VirtualRun, out: Path) -> dict[str, Path]:
    """Write ``frames.bin`` (the bytes the board sends), ``recording.csv`` (what ``acquire``
    would record), ``tracker_motive.csv`` (Motive export of the marker body), ``truth.csv``
    (exact, model frame, scenario clock), ``snapshot.vtu`` (truth mesh at peak load) and
    ``virtual.json`` (settings, seeds, offsets, the truth's peak figures)."""
    from softphantom import __version__
    from softphantom.evaluation import write_table
    from softphantom.sensing.protocol import PROTOCOL_VERSION
    from softphantom.sensing.recording import Recorder

    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {out}: cannot create ({exc.strerror})") from None
    paths = {k: out / v for k, v in dict(frames="frames.bin", recording="recording.csv",
                                         tracker="tracker_motive.csv", truth="truth.csv",
                                         snapshot="snapshot.vtu", meta="virtual.json").items()}
    paths["frames"].write_bytes(run.frame_bytes())
    src = run.source()
    if paths["recording"].exists():
        paths["recording"].unlink()
    b = run.config.board
    meta = {"softphantom": __version__, "protocol_version": PROTOCOL_VERSION,
            "firmware": ".".join(map(str, FIRMWARE)),
            "osr": b.osr, "p0_Pa": b.p0_Pa, "port": f"virtual:{run.scenario.name}",
            "tare": src.tare.to_dict(), "chain": run.chain.summary(), "virtual": True,
            "bench": host_bench(run.model, b).to_meta(), **scenario_contact(run.scenario)}
    with Recorder(paths["recording"], meta, layout=run.chain.layout) as rec:
        for m in src:
            rec.write(m)
    write_motive_csv(run.tracker, paths["tracker"], run.truth.marker_names, take_name=run.scenario.name)
    tmeta = {"softphantom": __version__, "kind": "virtual-truth", "scenario": run.scenario.name,
             "frame": "model (relative to rest)", "clock": "scenario (s)",
             "truth_mesh_nodes": len(run.truth.model.nodes), "truth_law": run.truth.summary()["law"],
             "truth_element_order": run.truth.model.element_order,
             "truth_mesh_size_mm": run.truth.model.design.mesh.size_mm,
             "patch_radius_mm": run.scenario.patch_radius_mm,
             "note": "truth solved at load keyframes, interpolated in load level (PCHIP) then mapped to time"}
    write_table(paths["truth"], tmeta, run.truth_columns())
    write_snapshot(run.truth, paths["snapshot"])
    paths["meta"].write_text(json.dumps(run_summary(run), indent=2) + "\n")
    return paths


def scenario_contact(sc: Scenario) -> dict:
    """The recording's ``contact``: the one point the scenario pushes at (a scenario without a push:
    the format's default, on-centre), or None with ``contacts`` listing them when it pushes at
    several (``estimate`` then asks for ``--at``).

    >>> from softphantom.virtual.scenario import scenario_from_dict
    >>> push = lambda p: {"point": p, "start_s": 1, "rise_s": 1, "force_N": [0, 1, 0]}
    >>> scenario_contact(scenario_from_dict({"name": "n", "duration_s": 3, "push": [push("port")]}, "n.toml"))
    {'contact': 'port'}
    >>> scenario_contact(scenario_from_dict({"name": "n", "duration_s": 3,
    ...                                      "push": [push("port"), push("on-centre")]}, "n.toml"))
    {'contact': None, 'contacts': ['on-centre', 'port']}
    """
    points = sorted({e.point for e in sc.events if e.kind == "push"})
    if len(points) > 1:
        return {"contact": None, "contacts": points}
    return {"contact": points[0] if points else Event.point}


def run_summary(run: VirtualRun) -> dict:
    """Settings, seeds, drawn offsets and the truth's peak figures (JSON-able)."""
    s, trk = run.signals, run.tracker
    return {
        "scenario": run.scenario.name, "source": run.scenario.source, "duration_s": run.scenario.duration_s,
        "truth": run.truth.summary(),
        "board": {"osr": run.config.board.osr, "rate_Hz": round(run.rate_Hz, 3), "kind": run.config.board_kind,
                  **({"mcu": run.config.board.mcu} if run.config.board_kind == "firmware" else {}),
                  "seed": run.config.board.seed,
                  "offsets_Pa": [round(float(x), 2) for x in s.offsets_Pa],
                  "drift_Pa_per_s": round(s.drift_Pa_per_s, 4),
                  "tube_tau_s": [round(float(x), 4) for x in s.tau_s],
                  "v_total_mm3": [round(float(x) * 1e9, 2) for x in s.chain.v_total_m3]},
        "tracker": {"rate_Hz": trk.config.rate_Hz, "noise_mm": trk.config.noise_mm,
                    "take_start_s": round(trk.take_start_s, 6), "latency_s": round(trk.latency_s, 6),
                    "clock_offset_s": round(trk.clock_offset_s, 6),
                    "lost_frames": int((~trk.valid).sum()), "frames": int(len(trk.valid)),
                    "seed": trk.config.seed},
    }
