"""Transducer + ratiometric ADC model, tare, and raw sums → :class:`Measurement`.

The transducers are ratiometric (output ∝ supply VS) and the UNO's ADC is referenced to the same
VS, so VS cancels: a code depends on the pressure only. Datasheet figures used (NXP):

* MPXV7002 (arms): Vout = VS·(0.2·P[kPa] + 0.5), rated −2 … +2 kPa, error band ±6.25 % of
  VFSS (= ±0.25 kPa; VFSS = 0.8·VS = 4 V at 5 V), mostly offset, which the tare removes.
* MPX4250D (the urethra, and any internal cavity): Vout = VS·(0.00369·P[kPa] + 0.04), rated 0 … 250 kPa, error
  ±(pressure error 3.45 kPa × temperature factor 1 over 0–85 °C), i.e. ±1.5 % VFSS.

An ideal 10-bit ADC returns code = floor(1024·Vin/VS) clipped to 0..1023; the board sums ``osr``
codes per channel. Derivations: docs/sensing.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from softphantom.errors import UserError
from softphantom.records.channels import BIP_LAYOUT, ChannelLayout, ChannelNames
from softphantom.records.names import BIP_CAVITIES
from softphantom.sensing.measurement import (
    ARM_CAVITY_VOLUMES_M3,
    P0_STANDARD_PA,
    TUBE_ID_M,
    TUBE_LENGTH_M,
    Measurement,
)
from softphantom.sensing.pneumatics import boyle_dV, tube_volume_m3

ADC_BITS = 10


@dataclass(frozen=True)
class Transducer:
    """A ratiometric pressure transducer: Vout/VS = k1·P[kPa] + k2 (datasheet transfer function).

    ``p_min_Pa``/``p_max_Pa`` the rated range, ``error_band_Pa`` the datasheet's total error band
    (± at 0–85 °C), ``source`` where the figures come from.
    """

    name: str
    k1_per_kPa: float
    k2: float
    p_min_Pa: float
    p_max_Pa: float
    error_band_Pa: float
    source: str

    def ratio(self, p_Pa):
        """Vout/VS for a gauge pressure (Pa)."""
        return self.k1_per_kPa * np.asarray(p_Pa, float) / 1000.0 + self.k2

    def pressure(self, ratio):
        """Gauge pressure (Pa) for Vout/VS."""
        return (np.asarray(ratio, float) - self.k2) / self.k1_per_kPa * 1000.0

    @property
    def adc_span_Pa(self) -> float:
        """Pressure change that sweeps the whole ADC range (Vout from 0 to VS): 1/k1 kPa."""
        return 1000.0 / self.k1_per_kPa

    @property
    def rated_span_Pa(self) -> float:
        return self.p_max_Pa - self.p_min_Pa


MPXV7002 = Transducer(
    "MPXV7002", 0.2, 0.5, -2000.0, 2000.0, 250.0,
    "NXP MPXV7002 datasheet: Vout = VS*(0.2*P[kPa] + 0.5) +/- 6.25 % VFSS",
)
MPX4250D = Transducer(
    "MPX4250D", 0.00369, 0.04, 0.0, 250_000.0, 3450.0,
    "NXP MPX4250D datasheet: Vout = VS*(0.00369*P[kPa] + 0.04) +/- (3.45 kPa x temp. factor)",
)


def board_transducers(layout: ChannelLayout) -> tuple[Transducer, ...]:
    """The transducers of a board of ``layout``: an MPXV7002 per volume channel, then an
    MPX4250D per actuated cavity (the BIP's: the urethra's)."""
    return (MPXV7002,) * len(layout.sensing) + (MPX4250D,) * len(layout.actuated)


def pa_to_counts(p_Pa, transducer: Transducer = MPXV7002, osr: int = 1, bits: int = ADC_BITS):
    """Expected oversampled raw sum for a gauge pressure (continuous; inverse of :func:`counts_to_pa`).

    With input noise of a code or more, the mean of floor(1024·r) is 1024·r − ½.

    >>> float(pa_to_counts(0.0, osr=100))        # MPXV7002 at 0 kPa: half scale, 100 readings
    51150.0
    """
    return osr * ((1 << bits) * transducer.ratio(p_Pa) - 0.5)


def counts_to_pa(raw, osr, transducer: Transducer = MPXV7002, bits: int = ADC_BITS):
    """Gauge pressure (Pa, nominal datasheet zero) from an oversampled raw sum.

    >>> round(float(counts_to_pa(51150 + 100 * 204.8, 100)))   # one kPa is 204.8 codes
    1000
    """
    raw = np.asarray(raw, float)
    return transducer.pressure((raw / np.asarray(osr, float) + 0.5) / (1 << bits))


def simulate_raw(p_Pa, osr: int, rng: np.random.Generator,
                 transducers: tuple[Transducer, ...] | None = None,
                 noise_codes: float = 0.5, bits: int = ADC_BITS) -> np.ndarray:
    """Raw sums a board would send for gauge pressures ``p_Pa`` (..., channels) at the transducers
    (default: the BIP's five, four arms and the urethra).

    Each of the ``osr`` readings per channel is floor(1024·r + noise) clipped to the ADC range,
    with Gaussian input noise of ``noise_codes`` (σ, in codes); pass a seeded ``rng``.

    >>> r = simulate_raw(np.zeros(5), 100, np.random.default_rng(0))
    >>> r.dtype.kind, r.shape, abs(int(r[0]) - 51150) < 50
    ('i', (5,), True)
    """
    if not isinstance(osr, (int, np.integer)) or osr < 1:
        raise UserError(f"osr must be a positive integer, got {osr!r}")
    tr = transducers or board_transducers(BIP_LAYOUT)
    p = np.asarray(p_Pa, float)
    if p.shape[-1] != len(tr):
        raise UserError(f"p (Pa): last axis must have {len(tr)} channels, got {p.shape}")
    ratio = np.stack([tr[i].ratio(p[..., i]) for i in range(len(tr))], axis=-1)
    x = (1 << bits) * ratio[..., None] + noise_codes * rng.standard_normal(p.shape + (osr,))
    codes = np.clip(np.floor(x), 0, (1 << bits) - 1).astype(np.int64)
    return codes.sum(axis=-1)


def channel_status(raw, osr: int, chain: SensorChain, margin: float = 0.1) -> str:
    """``"ok"`` or the first problem: ``invalid:<ch>`` (sum outside 0..1023·osr), ``rail:<ch>``
    (mean code within one code of 0 or 1023: channel disconnected, shorted or saturated), or
    ``range:<ch>`` (beyond the transducer's rated range by more than ``margin`` of its span);
    ``<ch>`` the ``chain``'s channel.

    >>> channel_status([51150, 51150, 51150, 51150, 0], 100, default_chain())
    'rail:urethra'
    """
    tr, bits, names = chain.transducers, chain.bits, chain.names
    full = (1 << bits) - 1
    raw = np.asarray(raw)
    for i, name in enumerate(names[: len(tr)]):
        r = int(raw[i])
        if r < 0 or r > full * osr:
            return f"invalid:{name}"
        mean = r / osr
        if mean <= 1.0 or mean >= full - 1.0:
            return f"rail:{name}"
        p = float(counts_to_pa(r, osr, tr[i], bits))
        slack = margin * tr[i].rated_span_Pa
        if p < tr[i].p_min_Pa - slack or p > tr[i].p_max_Pa + slack:
            return f"range:{name}"
    return "ok"


@dataclass(frozen=True, eq=False)
class SensorChain(ChannelNames):
    """Everything needed to turn raw sums into a :class:`Measurement` (except the tare).

    ``v_total_m3`` (n,) gas volume per volume channel (cavity + tube + dead volume), ``layout``
    the board's :class:`~softphantom.records.channels.ChannelLayout` (its volume channels, then
    its actuated cavities' pressures), ``transducers`` per channel (default: :func:`board_transducers`),
    ``bits`` ADC resolution.
    """

    v_total_m3: np.ndarray
    layout: ChannelLayout
    transducers: tuple[Transducer, ...] = ()
    bits: int = ADC_BITS

    def __post_init__(self) -> None:
        if not self.transducers:
            object.__setattr__(self, "transducers", board_transducers(self.layout))
        n = len(np.atleast_1d(self.v_total_m3))
        if len(self.transducers) != len(self.names) or n != len(self.layout.sensing):
            raise UserError(f"sensor chain: {n} volumes need one per volume channel and a transducer per channel "
                            f"({', '.join(self.names)}), got {len(self.transducers)} transducers")

    @property
    def names(self) -> tuple[str, ...]:
        """The board's channels in ADC order: the volume channels, then the actuated cavities."""
        return self.layout.channels

    @property
    def n_arms(self) -> int:
        return len(np.atleast_1d(self.v_total_m3))

    @property
    def n_channels(self) -> int:
        """The board's channels: the volume channels, then the actuated cavities."""
        return len(self.names)

    def summary(self) -> dict:
        return {"v_total_mm3": [round(float(v) * 1e9, 3) for v in self.v_total_m3],
                "transducers": [t.name for t in self.transducers], "adc_bits": self.bits, "names": list(self.names)}


def default_chain(cavity_volumes_m3=ARM_CAVITY_VOLUMES_M3, tube_length_m: float = TUBE_LENGTH_M,
                  tube_id_m: float = TUBE_ID_M, v_dead_m3: float = 0.0,
                  layout: ChannelLayout = BIP_LAYOUT) -> SensorChain:
    """The paper's chain (the BIP's layout: 4 arm cavities of 514, 514, 486, 486 mm³ each behind
    12 m × 1.2 mm tube, the urethra's pressure); for another ``layout``, one cavity volume per
    volume channel (an MPXV7002 each) and an MPX4250D per actuated cavity.

    >>> from softphantom.records.channels import ChannelLayout
    >>> [round(v * 1e9) for v in default_chain().v_total_m3]
    [14086, 14086, 14058, 14058]
    >>> default_chain([500e-9] * 3, layout=ChannelLayout(("a", "b", "c"), actuated=("urethra",))).names
    ('a', 'b', 'c', 'urethra')
    >>> default_chain([500e-9] * 3, layout=ChannelLayout(("a", "b", "c"))).n_channels
    3
    """
    vc = np.asarray(cavity_volumes_m3, float)
    n = len(layout.sensing)
    if vc.shape != (n,) or not np.all(np.isfinite(vc)) or np.any(vc <= 0):
        raise UserError(f"cavity volumes (m³): expected {n} positive values, got {cavity_volumes_m3!r}")
    return SensorChain(vc + tube_volume_m3(tube_length_m, tube_id_m) + float(v_dead_m3), layout)


@dataclass(frozen=True, eq=False)
class Tare:
    """Zero of each channel: ``offset_codes`` (channels,) mean ADC code per reading at rest,
    ``p0_Pa`` absolute ambient pressure at tare, ``n_samples`` frames used (0 = datasheet
    nominal), ``t_s`` host time of the window's end, ``noise_Pa`` (channels,) std over the window."""

    offset_codes: np.ndarray
    p0_Pa: float
    n_samples: int = 0
    t_s: float = math.nan
    noise_Pa: np.ndarray = field(default_factory=lambda: np.full(5, math.nan))

    def to_dict(self) -> dict:
        return {"offset_codes": [float(x) for x in self.offset_codes], "p0_Pa": self.p0_Pa,
                "n_samples": self.n_samples,
                "t_s": None if math.isnan(self.t_s) else self.t_s,
                "noise_Pa": [None if math.isnan(x) else float(x) for x in self.noise_Pa]}

    @staticmethod
    def from_dict(d: dict) -> "Tare":
        try:
            off = np.asarray(d["offset_codes"], float)
            if off.ndim != 1 or not 2 <= len(off) <= 16:
                raise ValueError("offset_codes needs one value per channel")
            noise = np.asarray([math.nan if x is None else x for x in d.get("noise_Pa", [None] * len(off))], float)
            return Tare(off, float(d["p0_Pa"]), int(d.get("n_samples", 0)),
                        math.nan if d.get("t_s") is None else float(d["t_s"]), noise)
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError(f"tare: malformed ({exc})") from None


def nominal_tare(chain: SensorChain, p0_Pa: float = P0_STANDARD_PA) -> Tare:
    """A tare from the datasheets' zero outputs (untared; offsets up to the error band)."""
    off = np.array([(1 << chain.bits) * t.k2 - 0.5 for t in chain.transducers])
    return Tare(off, float(p0_Pa), noise_Pa=np.full(len(off), math.nan))


class NotAtRestError(UserError):
    """The tare window is not at rest (the message says which channel and why)."""


MAX_BEND_PA = 0.5
"""An arm's pressure may bend (the RMS of its cubic trend off its straight line) by this much in a
tare window; a push held a little shorter than the window bends it by more (tests/test_defects_56a.py)."""


def window_bend_Pa(t_s, p) -> tuple[float, float]:
    """How far a window's cubic trend strays from its straight line (RMS, Pa: a push starting,
    ending or turning over bends it, a temperature drift does not), and what white noise alone
    reaches once in about 10⁹ windows (the two extra terms of the fit: σ² χ²₂ / n, χ²₂ ≤ 40; σ from
    the frame-to-frame differences).

    >>> t = np.arange(77) / 77.0
    >>> [round(b, 2) for b in window_bend_Pa(t, 3.0 * t)]   # a straight drift does not bend
    [0.0, 0.0]
    """
    t, p = np.asarray(t_s, float), np.asarray(p, float)
    if len(p) < 6 or not t[-1] > t[0]:
        return 0.0, math.inf
    x = (t - t.mean()) / (t[-1] - t[0])
    d = np.polyval(np.polyfit(x, p, 3), x) - np.polyval(np.polyfit(x, p, 1), x)
    sigma = float(np.std(np.diff(p))) / math.sqrt(2.0)
    return float(np.sqrt(np.mean(d * d))), sigma * math.sqrt(40.0 / len(p))


def tare_from_window(raw, osr, t_s, chain: SensorChain, p0_Pa: float = P0_STANDARD_PA,
                     max_std_Pa=None, max_slope_Pa_per_s=None, min_samples: int = 5, max_bend_Pa=None) -> Tare:
    """Zero offsets from a window of frames recorded at rest; refuses a window that is not.

    ``raw`` (n, channels) sums, ``osr`` scalar or (n,), ``t_s`` (n,) host times. At rest means:
    every frame in range, and per channel the pressure's standard deviation ≤ ``max_std_Pa``
    (default 25 Pa an arm, 500 Pa an internal cavity's), its least-squares slope ≤
    ``max_slope_Pa_per_s`` (default 20 and 2000 Pa/s; a push or a leak moves it; ≈ 5.8 Pa/s is
    1 K/min of temperature drift) and its bend (:func:`window_bend_Pa`) ≤ ``max_bend_Pa`` or
    what the noise explains (default :data:`MAX_BEND_PA` an arm, 20 Pa an internal cavity's): a
    window on the top of a push is steady on the whole, but bends where the push rises or falls.
    A load held steady through the whole window cannot be told from rest. Raises
    :class:`NotAtRestError` naming the channel.

    >>> rng = np.random.default_rng(1)
    >>> raw = simulate_raw(np.zeros((20, 5)), 100, rng)
    >>> tare = tare_from_window(raw, 100, np.arange(20) * 0.052, default_chain())
    >>> tare.n_samples, bool(abs(tare.offset_codes[0] - 511.5) < 0.2)
    (20, True)
    """
    raw = np.asarray(raw)
    t = np.asarray(t_s, float)
    n = raw.shape[0] if raw.ndim == 2 else 0
    c = chain.n_channels
    na = chain.n_arms
    max_std_Pa = (25.0,) * na + (500.0,) * (c - na) if max_std_Pa is None else max_std_Pa
    max_slope_Pa_per_s = (20.0,) * na + (2000.0,) * (c - na) if max_slope_Pa_per_s is None else max_slope_Pa_per_s
    max_bend_Pa = (MAX_BEND_PA,) * na + (20 * MAX_BEND_PA,) * (c - na) if max_bend_Pa is None else max_bend_Pa
    if raw.ndim != 2 or raw.shape[1] != c or t.shape != (n,):
        raise UserError(f"tare window: expected raw (n, {c}) and t (n,), got {raw.shape} and {t.shape}")
    if n < min_samples:
        raise NotAtRestError(f"tare window: {n} frames, need at least {min_samples}")
    if not np.all(np.isfinite(t)):
        raise UserError("tare window: t (s) not finite")
    osr_a = np.broadcast_to(np.asarray(osr, float), (n,))
    for k in range(n):
        st = channel_status(raw[k], int(osr_a[k]), chain)
        if st != "ok":
            raise NotAtRestError(f"tare window: frame {k} is {st}")
    codes = raw / osr_a[:, None]
    noise = np.empty(c)
    for i, name in enumerate(chain.names):
        p = chain.transducers[i].pressure(codes[:, i] / (1 << chain.bits))
        noise[i] = float(np.std(p))
        if noise[i] > max_std_Pa[i]:
            raise NotAtRestError(
                f"tare window: {name} not at rest (std {noise[i]:.1f} Pa > {max_std_Pa[i]:g} Pa)")
        if t[-1] > t[0]:
            slope = float(np.polyfit(t - t[0], p, 1)[0])
            if abs(slope) > max_slope_Pa_per_s[i]:
                raise NotAtRestError(f"tare window: {name} drifting ({slope:+.1f} Pa/s, limit "
                                     f"{max_slope_Pa_per_s[i]:g} Pa/s): a push, a leak or temperature")
        bend, noise_bend = window_bend_Pa(t, p)
        if bend > max(max_bend_Pa[i], noise_bend):
            raise NotAtRestError(f"tare window: {name} not at rest (its pressure bends by {bend:.1f} Pa, limit "
                                 f"{max(max_bend_Pa[i], noise_bend):.1f} Pa): a push rising, falling or held; tare "
                                 "with the phantom at rest")
    return Tare(codes.mean(axis=0), float(p0_Pa), n, float(t[-1]), noise)


def to_measurement(t: float, seq: int, t_board: float, raw, osr: int,
                   chain: SensorChain, tare: Tare) -> Measurement:
    """Convert one frame's raw sums to a :class:`Measurement` (tared gauge pressures, Boyle ΔV).

    >>> chain = default_chain(); tare = nominal_tare(chain)
    >>> raw = np.array([51150 + 20480, 51150, 51150, 51150, 100 * 40.46])  # +1 kPa on front_zpos
    >>> m = to_measurement(0.0, 7, 0.0, raw.astype(int), 100, chain, tare)
    >>> round(float(m.dp[0])), round(float(m.dV[0] * 1e9), 1), m.status
    (1000, -137.7, 'ok')
    """
    raw = np.asarray(raw, dtype=np.int64)
    c = chain.n_channels
    if raw.shape != (c,):
        raise UserError(f"raw: expected {c} channel sums, got shape {raw.shape}")
    if int(osr) < 1:
        raise UserError(f"osr: must be ≥ 1, got {osr}")
    status = channel_status(raw, int(osr), chain)
    codes = raw / float(osr)
    full = float(1 << chain.bits)
    p = np.array([(codes[i] - tare.offset_codes[i]) / (full * tr.k1_per_kPa) * 1000.0
                  for i, tr in enumerate(chain.transducers)])
    na = chain.n_arms
    dp = p[:na]
    if status.startswith("invalid"):
        dV = np.full(na, math.nan)
    else:
        dV = boyle_dV(dp, chain.v_total_m3, tare.p0_Pa)
    pressures = {c: float(v) for c, v in zip(chain.cavity_names, p[na:])}
    return Measurement(float(t), int(seq), float(t_board), raw, int(osr), dp, dV,
                       pressures.get(BIP_CAVITIES[0], math.nan), status,
                       None if chain.cavity_names == BIP_CAVITIES else pressures)
