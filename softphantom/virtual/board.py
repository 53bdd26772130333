"""The virtual sensing board: truth cavity volumes → the whole sensing chain → firmware frames.

Per arm (docs/sensing.md, DESIGN.md §4): the cavity's volume change ΔV compresses the gas of cavity
and tube, V_T = V_cavity + V_tube, isothermally: ΔP = P0·(V_T/(V_T + ΔV) − 1) (Boyle,
``boyle_dp``); the transducer at the far end of the 12 m tube sees it through the tube, a
distributed RC line simulated as a ladder of ``LADDER_SEGMENTS`` RC segments
(:meth:`~softphantom.sensing.tube.TubeLine.ladder_response` on a 1 kHz grid; mean delay τ from
``tube_time_constant_s``, ≈ 0.1 s); it adds its own zero offset (seeded, uniform within the datasheet's error band:
±250 Pa for the MPXV7002, ±3.45 kPa for the MPX4250D) and a slow common thermal drift (seeded,
``drift_K_per_min`` × P0/T per kelvin). An internal cavity's pump pressure (the BIP's urethra's)
reaches its MPX4250D directly, on the channels after the arms'.
The ADC takes ``osr`` readings per channel per frame, each ``floor(1024·Vout/VS + noise)`` with
Gaussian input noise (``noise_codes`` σ), and sums them (``simulate_raw``); the frame goes out as
the firmware sends it (``protocol.encode_data``: COBS + CRC-16), stamped with the board clock at
the window's centre, at the board's ADC-bound rate (``board.frame_rate_Hz``: 76.9 Hz at
``osr`` = 25, 19.2 Hz at 100). The board clock is the scenario clock (µs), so estimates land on
the truth's time axis; the first frame is preceded by an INFO frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softphantom.errors import UserError
from softphantom.sensing import P0_STANDARD_PA
from softphantom.sensing.measurement import TUBE_ID_M, TUBE_LENGTH_M
from softphantom.sensing.board import frame_rate_Hz
from softphantom.sensing.chain import MPX4250D, MPXV7002, SensorChain, default_chain, simulate_raw
from softphantom.sensing.pneumatics import boyle_dp, thermal_dp_per_K
from softphantom.sensing.tube import TubeLine
from softphantom.sensing.protocol import encode_data, encode_info

FIRMWARE = (2, 0, 0)
"""The firmware version the virtual board reports (protocol version 2)."""
LAG_GRID_S = 1e-3


@dataclass(frozen=True)
class BoardConfig:
    """Settings of the virtual board and its pneumatics (SI; seeded). ``offsets_Pa`` / ``drift``
    None = drawn from ``seed``: offsets uniform within each transducer's datasheet error band
    scaled by ``offset_band_fraction``, drift uniform in ±``drift_K_per_min``."""

    osr: int = 25
    seed: int = 0
    p0_Pa: float = P0_STANDARD_PA
    tube_length_m: float = TUBE_LENGTH_M
    tube_id_m: float = TUBE_ID_M
    noise_codes: float = 0.5
    offset_band_fraction: float = 1.0
    drift_K_per_min: float = 0.05
    tube_lag: bool = True
    #: per-channel sensitivity of the transducers relative to their datasheet (the arms, then the
    #: internal cavities; all 1: the datasheet's for any count): a gain of 1.05 reads 5 % high (for
    #: calibration studies)
    gains: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0)
    #: the Arduino the firmware is built for when the emulated firmware is the board (``virtual
    #: --board firmware --mcu``): "uno" (6 analog inputs) or "mega" (16)
    mcu: str = "uno"

    def __post_init__(self) -> None:
        from softphantom.virtual.firmware_sim import BOARDS

        if self.mcu not in BOARDS:
            raise UserError(f"--mcu: must be one of {', '.join(BOARDS)}, got {self.mcu!r}")
        if not 1 <= int(self.osr) <= 500:
            raise UserError(f"osr: must be 1..500 (the firmware's range), got {self.osr}")
        if not self.noise_codes >= 0:
            raise UserError(f"noise_codes: must be >= 0, got {self.noise_codes}")
        if not all(math.isfinite(g) and g > 0 for g in self.gains):
            raise UserError(f"gains: need positive values (the arms, then the internal cavities), got {self.gains}")

    def gains_for(self, n_channels: int) -> np.ndarray:
        """The gains of a board of ``n_channels`` (the datasheet's when all are 1)."""
        g = np.asarray(self.gains, float)
        if len(g) == n_channels:
            return g
        if np.all(g == 1.0):
            return np.ones(n_channels)
        raise UserError(f"gains: {len(g)} given for a board of {n_channels} channels (the arms, then the internal "
                        "cavities)")


@dataclass(frozen=True, eq=False)
class BoardSignals:
    """What the transducers see on the 1 kHz grid ``t`` (s): ``p_cavity`` (n, arms) Pa the Boyle
    pressure at the cavity, ``p_transducer`` (n, arms + M) Pa gauge at each transducer (lagged,
    with offset and drift; the last M columns the internal cavities), ``offsets_Pa`` (arms + M,),
    ``drift_Pa_per_s``, ``tau_s`` (arms,) tube time constants, ``chain`` the chain the physics
    used (its ``names``: the channels)."""

    t: np.ndarray
    p_cavity: np.ndarray
    p_transducer: np.ndarray
    offsets_Pa: np.ndarray
    drift_Pa_per_s: float
    tau_s: np.ndarray
    chain: SensorChain


def board_signals(truth, cavity_volumes_m3, config: BoardConfig = BoardConfig()) -> BoardSignals:
    """Pressures at the transducers over the scenario on a 1 kHz grid (see the module docstring).
    ``truth`` is a :class:`~softphantom.virtual.truth.Truth`; the board's channels are its model's
    layout (:class:`~softphantom.records.channels.ChannelLayout`): ``cavity_volumes_m3`` (n,) the
    volume channels' cavities the physics uses (the truth mesh's), in the sensor order (the arms,
    then any measured internal cavity); a pressure channel per actuated cavity follows them."""
    rng = np.random.default_rng([config.seed, 1])
    layout = truth.model.layout
    na = len(layout.sensing)
    cols = [truth.model.design.cavity_names.index(a) for a in layout.sensing]  # truth dV: arms, then every internal
    chain = default_chain(cavity_volumes_m3, config.tube_length_m, config.tube_id_m, layout=layout)
    dur = truth.scenario.duration_s
    t = np.arange(0.0, dur + 0.5 + LAG_GRID_S / 2, LAG_GRID_S)
    ts = truth.sample(t)
    p_cav = boyle_dp(ts.dV[:, cols], chain.v_total_m3, config.p0_Pa)
    lines = [TubeLine.of(config.tube_length_m, config.tube_id_m, v, config.p0_Pa) for v in cavity_volumes_m3]
    tau = np.array([line.elmore_s for line in lines])
    if config.tube_lag:
        p_arm = np.column_stack([lines[i].ladder_response(p_cav[:, i], LAG_GRID_S)
                                 for i in range(na)])
    else:
        p_arm = p_cav
    cav = layout.actuated
    nc = na + len(cav)
    bands = np.array([MPXV7002.error_band_Pa] * na + [MPX4250D.error_band_Pa] * len(cav)) * config.offset_band_fraction
    offsets = rng.uniform(-1.0, 1.0, nc) * bands
    drift = rng.uniform(-1.0, 1.0) * config.drift_K_per_min / 60.0 * thermal_dp_per_K(config.p0_Pa)
    p = np.column_stack([p_arm, ts.pressures]) * config.gains_for(nc) + offsets
    p[:, :na] += drift * t[:, None]
    return BoardSignals(t, p_cav, p, offsets, float(drift), tau, chain)


class VirtualBoard:
    """Frames of the virtual board, on demand: :meth:`frames` gives the bytes of the DATA frames
    whose window centre lies in [t_from, t_to) (scenario clock), continuing ``seq`` and the
    seeded noise. ``osr`` may be changed between calls (as SET_OSR does on the real board)."""

    def __init__(self, signals: BoardSignals, config: BoardConfig = BoardConfig()):
        self.signals = signals
        self.config = config
        self.osr = int(config.osr)
        self._rng = np.random.default_rng([config.seed, 2])
        self.seq = 0
        self._next_t = 0.5 / self.rate_Hz  # centre of the first window
        self.duration_s = float(signals.t[-1]) - 0.5

    @property
    def n_channels(self) -> int:
        """The board's channels: the arms, then the internal cavities."""
        return self.signals.chain.n_channels

    @property
    def rate_Hz(self) -> float:
        return frame_rate_Hz(self.osr, n_channels=self.n_channels)

    def info(self) -> bytes:
        """An INFO frame (firmware version, channel count, current OSR)."""
        return encode_info(self.seq & 0xFFFF, int(round(self._next_t * 1e6)) & 0xFFFFFFFF, FIRMWARE,
                           self.n_channels, self.osr)

    def set_osr(self, osr: int) -> None:
        if not 1 <= int(osr) <= 500:
            raise UserError(f"osr: must be 1..500, got {osr}")
        self.osr = int(osr)

    def raw_at(self, t: np.ndarray) -> np.ndarray:
        """(n, channels) oversampled sums for window centres ``t`` (advances the noise generator)."""
        s = self.signals
        tt = np.clip(t, s.t[0], s.t[-1])
        p = np.column_stack([np.interp(tt, s.t, s.p_transducer[:, i]) for i in range(self.n_channels)])
        return simulate_raw(p, self.osr, self._rng, s.chain.transducers, self.config.noise_codes)

    def frames(self, t_to: float) -> tuple[bytes, np.ndarray]:
        """Frame bytes for every window centre up to ``t_to`` (s) not sent yet, and their times."""
        dt = 1.0 / self.rate_Hz
        n = max(0, int(math.floor((t_to - self._next_t) / dt)) + 1)
        if n == 0:
            return b"", np.zeros(0)
        t = self._next_t + dt * np.arange(n)
        raw = self.raw_at(t)
        out = bytearray()
        for k in range(n):
            out += encode_data(self.seq & 0xFFFF, int(round(t[k] * 1e6)) & 0xFFFFFFFF, self.osr, raw[k])
            self.seq += 1
        self._next_t = float(t[-1] + dt)
        return bytes(out), t


def arm_volumes(model) -> np.ndarray:
    """(channels,) m³, the volume channels' cavity volumes of a PhantomModel in the sensor order
    (the arms, then any measured internal cavity)."""
    return np.array([model.cavity_volume(a) for a in model.layout.sensing])
