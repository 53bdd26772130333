"""The board's own firmware in an AVR emulator: ``firmware/build/bip_sensing.elf`` run by simavr.

:class:`FirmwareSim` drives the harness ``firmware/sim/fw_sim.c`` (built on demand by
``make -C firmware BOARD=uno|mega N_CHANNELS=n sim``; it needs the Debian packages ``simavr`` and
``libsimavr-dev``): the host gives the voltages at the n ADC inputs on a time grid and the bytes it
sends, the emulated MCU (the UNO's ATmega328P or the Mega's ATmega2560, :data:`BOARDS`) runs until a
given time, and the bytes the firmware sent come back with the emulator cycle at which each was
written. Time is the emulator's cycle count (16 MHz, so the board clock
``t_us`` is cycles / 16 from reset). Each ADC conversion takes its channel's voltage at its start
(linear between grid points) and quantizes it as the datasheet does, floor(1024·V/VS + noise).

:class:`FirmwareBoard` has the interface of :class:`~softphantom.virtual.board.VirtualBoard`, so
``softphantom virtual run|serve --board firmware`` feeds the virtual transducers' voltages to the
real firmware instead of the Python model of it.
"""

from __future__ import annotations

import shutil
import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softphantom.errors import UserError
from softphantom.sensing.board import F_CPU_HZ, frame_rate_Hz
from softphantom.sensing.protocol import (N_CHANNELS, DataFrame, StreamDecoder, check_channels, encode_get_info,
                                         encode_set_osr)

FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware"
SIMAVR_HEADER = Path("/usr/include/simavr/sim_avr.h")
VS_V = 5.0
"""The transducers' supply, which is also the ADC's reference (AVcc): readings are ratiometric."""



@dataclass(frozen=True)
class Arduino:
    """A board the firmware is built for (``make BOARD=name``): its MCU and analog inputs."""

    name: str
    label: str
    mcu: str
    analog_inputs: int
    pins: str


BOARDS = {"uno": Arduino("uno", "Arduino UNO", "atmega328p", 6, "A0-A5"),
          "mega": Arduino("mega", "Arduino Mega 2560", "atmega2560", 16, "A0-A15")}
"""The boards the firmware builds for; both run at 16 MHz, their USB serial on USART0."""
DEFAULT_BOARD = "uno"


def check_board(board: str, n_channels: int, cavity_names: tuple[str, ...] = ("urethra",)) -> Arduino:
    """The board named ``board`` if it has an analog input for each of ``n_channels`` (the arms,
    then a pressure channel per internal cavity of ``cavity_names``), else a one-line UserError
    naming both counts.

    >>> check_board("mega", 9).mcu
    'atmega2560'
    >>> check_board("uno", 7)
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --mcu uno: the Arduino UNO has 6 analog inputs (A0-A5), the design needs 7 channels (6 arms and the urethra); --mcu mega has 16
    >>> check_board("uno", 7, ("urethra", "tumour"))
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --mcu uno: the Arduino UNO has 6 analog inputs (A0-A5), the design needs 7 channels (5 arms and 2 internal cavities: urethra, tumour); --mcu mega has 16
    """
    b = BOARDS.get(board)
    if b is None:
        raise UserError(f"--mcu: must be one of {', '.join(BOARDS)}, got {board!r}")
    n = n_channels
    if isinstance(n, int) and n > b.analog_inputs:  # before the protocol's limit, which is the Mega's
        more = [o for o in BOARDS.values() if o.analog_inputs >= n]
        hint = f"; --mcu {more[0].name} has {more[0].analog_inputs}" if more else ""
        cav = tuple(cavity_names)
        what = (f"{n - len(cav)} arms" + (f" and the {cav[0]}" if len(cav) == 1 else
                                          f" and {len(cav)} internal cavities: {', '.join(cav)}" if cav else ""))
        raise UserError(f"--mcu {b.name}: the {b.label} has {b.analog_inputs} analog inputs ({b.pins}), the design "
                        f"needs {n} channels ({what}){hint}")
    check_channels(n)
    return b


_TX = np.dtype([("cycle", "<u8"), ("byte", "u1")])
_ADC = np.dtype([("cycle", "<u8"), ("ch", "u1"), ("code", "<u2")])


class SimavrMissing(UserError):
    """simavr (or the AVR toolchain) is not installed."""


def simavr_missing() -> str | None:
    """The one-line reason the emulated board cannot run here, or None if it can."""
    if not SIMAVR_HEADER.exists():
        return "simavr not installed: apt-get install simavr libsimavr-dev (scripts/install-system-deps.sh)"
    if shutil.which("avr-gcc") is None:
        return "avr-gcc not installed: apt-get install gcc-avr avr-libc binutils-avr (scripts/install-system-deps.sh)"
    if shutil.which("make") is None or shutil.which("gcc") is None:
        return "make/gcc not installed: apt-get install make gcc"
    return None


def build(build_dir: Path | None = None, n_channels: int = N_CHANNELS,
          board: str = DEFAULT_BOARD, cavity_names: tuple[str, ...] = ("urethra",)) -> tuple[Path, Path]:
    """(harness, firmware .elf) for a ``board`` (:data:`BOARDS`) of ``n_channels``, built by ``make
    -C firmware BOARD=board N_CHANNELS=n sim`` if out of date (in firmware/build for the BIP's UNO
    of 5, else build_<n> on the UNO, build_mega_<n> on the Mega)."""
    b = check_board(board, n_channels, cavity_names)
    why = simavr_missing()
    if why:
        raise SimavrMissing(why)
    if not (FIRMWARE_DIR / "Makefile").exists():
        raise UserError(f"--board firmware: the firmware sources are not at {FIRMWARE_DIR} (a source checkout is needed)")
    n = n_channels
    if not build_dir:
        sub = "build" if n == N_CHANNELS else f"build_{n}"
        build_dir = FIRMWARE_DIR / (sub if b.name == DEFAULT_BOARD else f"build_{b.name}_{n}")
    r = subprocess.run(["make", "-s", "-C", str(FIRMWARE_DIR), f"BUILD={Path(build_dir).resolve()}", f"BOARD={b.name}",
                        f"N_CHANNELS={n}", "sim"], capture_output=True, text=True)
    if r.returncode:
        last = (r.stderr.strip() or r.stdout.strip()).splitlines()[-1:] or ["?"]
        raise UserError(f"--board firmware: building the emulator harness failed: {last[0]}")
    return Path(build_dir) / "fw_sim", Path(build_dir) / "bip_sensing.elf"


@dataclass(frozen=True, eq=False)
class SimOutput:
    """What one :meth:`FirmwareSim.run_until` produced: the emulator ``cycle`` at its end, the
    bytes the firmware sent (``data``) with the cycle of each (``byte_cycles``), and with
    ``log_adc`` the conversions started (``adc``: fields cycle, ch, code)."""

    cycle: int
    data: bytes
    byte_cycles: np.ndarray
    adc: np.ndarray


class FirmwareSim:
    """A running emulated board (a subprocess; use as a context manager or call :meth:`close`).

    ``elf`` the firmware (default: built from ``firmware/`` for ``board`` and ``n_channels``; a
    given ``elf`` and ``harness`` must be built for both), ``noise_codes`` Gaussian ADC input noise
    (σ, codes; seeded by ``seed``), ``log_adc`` return every conversion."""

    def __init__(self, elf: Path | None = None, *, harness: Path | None = None, vs_V: float = VS_V,
                 noise_codes: float = 0.0, seed: int = 0, log_adc: bool = False, n_channels: int = N_CHANNELS,
                 board: str = DEFAULT_BOARD):
        self.n_channels = check_channels(n_channels)
        self.board = check_board(board, self.n_channels)
        if elf is None or harness is None:
            h, e = build(n_channels=self.n_channels, board=board)
            harness, elf = harness or h, elf or e
        args = [str(harness), str(elf), "--vs", repr(float(vs_V)), "--noise", repr(float(noise_codes)),
                "--seed", str(int(seed))]
        if log_adc:
            args.append("--log-adc")
        self._p = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.cycle = 0

    @staticmethod
    def cycles(t_s) -> np.ndarray:
        return np.round(np.asarray(t_s, float) * F_CPU_HZ).astype(np.uint64)

    def set_voltages(self, t_s, volts) -> None:
        """Voltages (n, channels) V at the ADC inputs from times ``t_s`` (n,) on (increasing, after
        any earlier point); linear between points, the last one held."""
        c = self.n_channels
        v = np.asarray(volts, float).reshape(-1, c)
        rec = np.zeros(len(v), dtype=[("cycle", "<u8"), ("v", "<f8", (c,))])
        rec["cycle"], rec["v"] = self.cycles(t_s), v
        self._write(b"V" + struct.pack("<I", len(rec)) + rec.tobytes())

    def send(self, data: bytes) -> None:
        """Bytes host → board (delivered at the wire's rate from the current emulator time)."""
        if data:
            self._write(b"U" + struct.pack("<I", len(data)) + bytes(data))

    def run_until(self, t_s: float) -> SimOutput:
        """Run the emulated CPU up to time ``t_s`` (s since reset)."""
        until = max(int(self.cycles(t_s)), self.cycle)
        self._write(b"R" + struct.pack("<Q", until))
        cycle, n = struct.unpack("<QI", self._read(12))
        tx = np.frombuffer(self._read(n * _TX.itemsize), _TX)
        (m,) = struct.unpack("<I", self._read(4))
        adc = np.frombuffer(self._read(m * _ADC.itemsize), _ADC)
        self.cycle = cycle
        return SimOutput(cycle, tx["byte"].tobytes(), tx["cycle"].copy(), adc.copy())

    def close(self) -> None:
        if self._p.poll() is None:
            try:
                self._p.stdin.write(b"Q")
                self._p.stdin.close()
            except OSError:
                pass
            try:
                self._p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._p.kill()
                self._p.wait()

    def __enter__(self) -> "FirmwareSim":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _write(self, b: bytes) -> None:
        try:
            self._p.stdin.write(b)
            self._p.stdin.flush()
        except BrokenPipeError:
            raise UserError(f"emulated board: the harness ended (exit {self._p.wait()})") from None

    def _read(self, n: int) -> bytes:
        out = self._p.stdout.read(n) if n else b""
        if len(out) != n:
            raise UserError(f"emulated board: the harness ended (exit {self._p.wait()})")
        return out


class FirmwareBoard:
    """The emulated firmware as a virtual board: the interface of
    :class:`~softphantom.virtual.board.VirtualBoard` (``frames``, ``info``, ``set_osr``,
    ``rate_Hz``, ``seq``, ``duration_s``) plus :meth:`receive` for the host's raw bytes.

    The transducers' output voltages come from ``signals`` (the 1 kHz grid of
    :func:`~softphantom.virtual.board.board_signals`); noise, seed and the board the firmware is
    built for (``config.mcu``, :data:`BOARDS`) from ``config``. The firmware
    starts at its default OSR (100) and announces itself with an INFO frame; a ``config.osr``
    other than that is set with SET_OSR before the first window, as the host's ``acquire`` does.
    Frames come out when the firmware sends them (after their window), stamped by its own clock."""

    LEAD_S = 0.2  # voltages are sent this far ahead of the emulator
    UART_READY_S = 0.001

    def __init__(self, signals, config, *, elf: Path | None = None, harness: Path | None = None):
        self.signals = signals
        self.config = config
        self.osr = int(config.osr)
        self.seq = 0
        self.duration_s = float(signals.t[-1]) - 0.5
        tr = signals.chain.transducers
        p = signals.p_transducer
        n = len(tr)  # the board's channels: the arms, then the internal cavities
        self._volts = VS_V * np.column_stack([tr[i].ratio(p[:, i]) for i in range(n)])
        self._sent_to = 0  # grid points already given to the emulator
        check_board(config.mcu, n, signals.chain.cavity_names)  # the message names the design's cavities
        self._sim = FirmwareSim(elf, harness=harness, noise_codes=config.noise_codes, seed=config.seed, n_channels=n,
                                board=config.mcu)
        self._dec = StreamDecoder(n)
        self._feed(self.LEAD_S)
        self._pending = b""
        if self.osr != 100:  # once its UART is on (it drops what arrives before, as the chip does)
            self._pending = self._sim.run_until(self.UART_READY_S).data
            self._sim.send(encode_set_osr(self.osr))

    @property
    def rate_Hz(self) -> float:
        return frame_rate_Hz(self.osr, n_channels=self._sim.n_channels)

    def _feed(self, t_to: float) -> None:
        t = self.signals.t
        k = int(np.searchsorted(t, t_to, side="right"))
        if k > self._sent_to:
            self._sim.set_voltages(t[self._sent_to:k], self._volts[self._sent_to:k])
            self._sent_to = k

    def frames(self, t_to: float) -> tuple[bytes, np.ndarray]:
        """The bytes the firmware sent up to ``t_to`` (s) and the window centres (s, its clock) of
        the DATA frames among them."""
        self._feed(t_to + self.LEAD_S)
        data = self._pending + self._sim.run_until(t_to).data
        self._pending = b""
        fr = [f for f in self._dec.feed(data) if isinstance(f, DataFrame)]
        self.seq += len(fr)
        if fr:
            self.osr = fr[-1].osr
        return data, np.array([f.t_us * 1e-6 for f in fr])

    def info(self) -> bytes:
        """The firmware sends its own INFO frames (after reset, on request): nothing to add here."""
        return b""

    def receive(self, data: bytes) -> None:
        """Bytes from the host (commands) to the firmware's UART."""
        self._sim.send(data)

    def set_osr(self, osr: int) -> None:
        if not 1 <= int(osr) <= 500:
            raise UserError(f"osr: must be 1..500, got {osr}")
        self._sim.send(encode_set_osr(int(osr)))

    def get_info(self) -> None:
        self._sim.send(encode_get_info())

    def close(self) -> None:
        self._sim.close()

    def __del__(self) -> None:
        try:
            self._sim.close()
        except Exception:
            pass
