"""The board's own firmware (firmware/main.c) run in simavr, read through the host's decoder.

Each check below runs on the real firmware and, in ``test_a_broken_firmware_fails``, on a
deliberately broken copy of main.c (one line changed): every check must catch its fault.
Time is the emulator's cycle count (16 MHz); a run of a few emulated seconds takes about a second.
"""

from __future__ import annotations

import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from softphantom.records import ChannelLayout
from softphantom.sensing.board import frame_rate_Hz
from softphantom.sensing.protocol import (
    DataFrame,
    InfoFrame,
    StreamDecoder,
    encode_get_info,
    encode_set_osr,
    frame,
)
from softphantom.virtual.firmware_sim import FIRMWARE_DIR, VS_V, FirmwareSim, build, simavr_missing

F_CPU = 16e6
CONV_CYCLES = 13 * 128          # one conversion: 13 ADC clocks at prescaler 128 = 104 µs
CLOCK_TOLERANCE = 5e-3          # the UNO's ceramic resonator (docs/protocol.md)


@dataclass(frozen=True)
class Tools:
    harness: Path
    elf: Path


@pytest.fixture(scope="module")
def tools(tmp_path_factory) -> Tools:
    why = simavr_missing()
    if why:
        pytest.skip(why)
    h, e = build(tmp_path_factory.mktemp("fwsim"))
    return Tools(h, e)


@dataclass
class Run:
    frames: list            # decoded frames in order (INFO and DATA)
    arrival: list           # emulator cycle of each frame's last byte
    adc: np.ndarray         # conversions (cycle, ch, code)
    decoder: StreamDecoder

    @property
    def data(self) -> list[DataFrame]:
        return [f for f in self.frames if isinstance(f, DataFrame)]

    @property
    def infos(self) -> list[InfoFrame]:
        return [f for f in self.frames if isinstance(f, InfoFrame)]


def run_fw(tools: Tools, t_end_s: float, volts=None, commands=(), log_adc=False, step_s=0.01) -> Run:
    """Run the firmware to ``t_end_s`` with ``volts`` (t grid, (n, 5)) and ``commands`` [(t_s, bytes)]."""
    dec = StreamDecoder()
    frames, arrival, adc = [], [], []
    pending = sorted(commands, key=lambda c: c[0])
    with FirmwareSim(tools.elf, harness=tools.harness, log_adc=log_adc) as sim:
        if volts is not None:
            sim.set_voltages(*volts)
        t = 0.0
        while True:
            while pending and pending[0][0] <= t + 1e-12:
                sim.send(pending.pop(0)[1])
            if t >= t_end_s - 1e-12:
                break
            t = min(t_end_s, t + step_s, *(c[0] for c in pending))
            out = sim.run_until(t)
            for i, b in enumerate(out.data):      # byte by byte: each frame's arrival cycle
                for f in dec.feed(bytes([b])):
                    frames.append(f)
                    arrival.append(int(out.byte_cycles[i]))
            adc.append(out.adc)
    return Run(frames, arrival, np.concatenate(adc) if adc else np.zeros(0), dec)


def const_volts(codes) -> tuple:
    """Voltages in the middle of each code's step."""
    v = (np.asarray(codes, float) + 0.5) * VS_V / 1024
    return np.array([0.0]), v[None, :]


def ramp_volts(t_end_s: float):
    """Five different slow ramps (one code every few conversions): every reading is different."""
    t = np.linspace(0.0, t_end_s, 64)
    base = np.array([0.3, 1.1, 2.0, 2.9, 3.7])
    slope = np.array([1.0, -0.8, 0.6, -0.4, 0.9])         # V/s
    return t, base + slope * t[:, None]


def expected_code(volts, cycle, ch) -> int:
    t, v = volts
    x = np.interp(cycle / F_CPU, t, v[:, ch])
    return int(min(1023, max(0, np.floor(1024 * x / VS_V))))


def windows(run: Run, skip_first_conversion=True):
    """The conversions of each DATA frame's window: consecutive runs of 5·N after the first."""
    conv = run.adc[1:] if skip_first_conversion else run.adc
    out, k = [], 0
    for f in run.data:
        n = 5 * f.osr
        out.append(conv[k:k + n])
        k += n
    return out


# --- the checks (each also run on a broken firmware) -----------------------------------------------

def check_rate(tools: Tools):
    """19.2 Hz at N = 100 (the default), 76.9 Hz at 25, on the emulator's clock."""
    run = run_fw(tools, 1.6, const_volts([100, 200, 300, 400, 500]), commands=[(0.8, encode_set_osr(25))])
    for osr, n_min in ((100, 10), (25, 30)):
        cyc = np.array([a for f, a in zip(run.frames, run.arrival) if isinstance(f, DataFrame) and f.osr == osr])
        assert len(cyc) >= n_min, f"OSR {osr}: {len(cyc)} frames"
        rate = F_CPU / np.median(np.diff(cyc[1:]))
        assert abs(rate / frame_rate_Hz(osr) - 1) < CLOCK_TOLERANCE, (osr, rate)
        t_us = np.array([f.t_us for f in run.data if f.osr == osr], float)
        board_rate = 1e6 / np.median(np.diff(t_us[1:]))       # and on the board's own clock
        assert abs(board_rate / frame_rate_Hz(osr) - 1) < CLOCK_TOLERANCE, (osr, board_rate)


def check_sums(tools: Tools):
    """Summed counts bit-exact: N·code for constant inputs (incl. both rails), and for five ramps
    the sum of floor(1024·V/VS) at each conversion's start."""
    codes = [0, 1, 511, 1000, 1023]
    run = run_fw(tools, 0.5, (np.array([0.0]), np.array([[0.0, 1.5 * VS_V / 1024, 511.5 * VS_V / 1024,
                                                          1000.5 * VS_V / 1024, VS_V]])))
    assert len(run.data) >= 8
    for f in run.data:
        assert f.raw == tuple(f.osr * c for c in codes), f
    volts = ramp_volts(0.6)
    run = run_fw(tools, 0.6, volts, commands=[(0.002, encode_set_osr(25))], log_adc=True)
    assert len(run.data) >= 30
    for f, w in zip(run.data, windows(run)):
        assert len(w) == 5 * f.osr
        assert list(w["ch"]) == [0, 1, 2, 3, 4] * f.osr, f"channel order in frame {f.seq}"
        exp = [sum(expected_code(volts, int(c), ch) for c in w["cycle"][w["ch"] == ch]) for ch in range(5)]
        assert list(f.raw) == exp, (f.seq, f.raw, exp)


def check_timestamps(tools: Tools):
    """t_us is the centre of the frame's sampling window (first conversion's start to last one's
    end), on the emulator's clock within 0.3 ms (simavr's Timer1 reads carry an offset of ~0.1 ms),
    and exactly by the step across an OSR change: (52.0 + 13.0) / 2 ms from the last N = 100
    window's centre to the first N = 25 one's."""
    run = run_fw(tools, 0.5, const_volts([1, 2, 3, 4, 5]), commands=[(0.2, encode_set_osr(25))], log_adc=True)
    assert len(run.data) >= 10
    for f, w in zip(run.data, windows(run)):
        centre_us = (int(w["cycle"][0]) + int(w["cycle"][-1]) + CONV_CYCLES) / 2 / 16
        assert abs(f.t_us - centre_us) < 300, (f.seq, f.t_us, centre_us)
    seq = [f.osr for f in run.data]
    k = seq.index(25)
    assert seq[k - 1] == 100
    step_us = run.data[k].t_us - run.data[k - 1].t_us
    assert abs(step_us - (52_000 + 13_000) / 2) < 0.002 * 32_500, step_us


def check_commands(tools: Tools):
    """SET_OSR and GET_INFO of protocol versions 1 and 2: each answered by an INFO (firmware 2.0.0,
    5 channels, the N in force, seq of the next DATA frame); an out-of-range SET_OSR changes
    nothing; DATA frames follow the new N."""
    bad = frame(struct.pack("<BBH", 2, 0x10, 501))
    cmds = [(0.06, encode_get_info(version=1)), (0.12, encode_set_osr(25, version=1)),
            (0.2, encode_get_info(version=2)), (0.26, encode_set_osr(40, version=2)),
            (0.34, bad), (0.4, encode_set_osr(10, version=1))]
    run = run_fw(tools, 0.5, const_volts([10, 20, 30, 40, 50]), commands=cmds)
    infos = run.infos
    assert [i.osr for i in infos] == [100, 100, 25, 25, 40, 40, 10], infos   # reset INFO + 6 answers
    assert all(i.firmware == (2, 0, 0) and i.n_channels == 5 for i in infos)
    for i, f in enumerate(run.frames):
        if isinstance(f, InfoFrame) and i > 0:
            nxt = next((g for g in run.frames[i + 1:] if isinstance(g, DataFrame)), None)
            assert nxt is None or nxt.seq == f.seq, (f, nxt)
    osrs = [f.osr for f in run.data]
    assert set(osrs) == {100, 25, 40, 10}
    assert osrs == sorted(osrs, key=[100, 25, 40, 10].index), osrs       # in the order they were set
    assert run.decoder.stats.frames_lost == 0 and run.decoder.stats.rejected == 0


def check_tx_while_sampling(tools: Tools):
    """At N = 25 and at N = 6 (the UART 94 % busy) the ADC converts back to back, 104 µs apart,
    while frames are packed and sent: frames go out during the next window, no conversion is
    missed or shifted, no frame lost, and every frame's sums are those of its 5·N conversions."""
    volts = ramp_volts(0.5)
    run = run_fw(tools, 0.5, volts, commands=[(0.002, encode_set_osr(25)), (0.3, encode_set_osr(6))], log_adc=True)
    assert run.decoder.stats.frames_lost == 0 and run.decoder.stats.rejected == 0, run.decoder.stats
    gaps = np.diff(run.adc["cycle"][1:].astype(np.int64))
    assert gaps.max() <= CONV_CYCLES + 8 and gaps.min() >= CONV_CYCLES - 8, (gaps.min(), gaps.max())
    n6 = 0
    for f, w in zip(run.data, windows(run)):
        exp = [sum(expected_code(volts, int(c), ch) for c in w["cycle"][w["ch"] == ch]) for ch in range(5)]
        assert list(f.raw) == exp, (f.seq, f.osr)
        n6 += f.osr == 6
    assert n6 >= 40
    inside = [a for f, a in zip(run.frames, run.arrival) if isinstance(f, DataFrame)]
    conv = run.adc["cycle"]
    assert all(((conv > a - 2000) & (conv < a + 2000)).sum() >= 2 for a in inside)  # TX amid conversions


def check_command_burst(tools: Tools):
    """Twenty commands back to back (150 bytes, over twice the 64-byte RX ring; their INFO answers
    keep the UART busy for 32 ms) while streaming at N = 25: every one answered in order, no DATA
    frame lost, the last N in force."""
    burst, expect = [], [100, 25]
    for k in range(20):
        version = 1 + k % 4 // 2
        if k % 2:
            burst.append(encode_set_osr(26 + k, version=version))
        else:
            burst.append(encode_get_info(version=version))
        expect.append(26 + k if k % 2 else expect[-1])
    blob = b"".join(burst)
    assert len(blob) == 150
    run = run_fw(tools, 0.6, const_volts([5, 6, 7, 8, 9]), commands=[(0.002, encode_set_osr(25)), (0.2, blob)])
    assert [i.osr for i in run.infos] == expect, run.infos
    st = run.decoder.stats
    assert st.frames_lost == 0 and st.rejected == 0, st
    assert run.data[-1].osr == 45 and len(run.data) >= 25


CHECKS = {"rate": check_rate, "sums": check_sums, "timestamps": check_timestamps, "commands": check_commands,
          "tx_while_sampling": check_tx_while_sampling, "command_burst": check_command_burst}


@pytest.mark.parametrize("name", list(CHECKS))
def test_real_firmware(tools, name):
    CHECKS[name](tools)


# (check, the line of main.c, its broken version)
MUTANTS = {
    "osr_off_by_one": (["rate", "sums"], "++acc_k < acc_n", "++acc_k <= acc_n"),
    "timestamp_at_window_start": (["timestamps"], "done_t_us = t_window_start + (t_end - t_window_start) / 2u;",
                                  "done_t_us = t_window_start;"),
    "channels_shifted": (["sums"], "    ch_conv = ch_mux;\n", "    ch_conv = ch;\n"),
    "v1_commands_ignored": (["commands", "command_burst"], "payload[0] < SP_PROTOCOL_VERSION_MIN",
                            "payload[0] < SP_PROTOCOL_VERSION"),
    "get_info_ignored": (["commands"], "payload[1] == SP_CMD_GET_INFO && len == 2",
                         "payload[1] == SP_CMD_GET_INFO && len == 3"),
    "sampling_paused_while_sending": (["tx_while_sampling"], "            size_t len = sp_pack_data(",
                                      "            cli();\n            size_t len = sp_pack_data("),
    "rx_ring_too_small": (["command_burst"], "#define RXBUF 64u", "#define RXBUF 8u"),
}


@pytest.mark.parametrize("mutant", list(MUTANTS))
def test_a_broken_firmware_fails(tools, tmp_path, mutant):
    checks, good, bad = MUTANTS[mutant]
    src = (FIRMWARE_DIR / "main.c").read_text()
    assert src.count(good) == 1, f"main.c no longer has {good!r}: update the mutant"
    if mutant == "sampling_paused_while_sending":   # interrupts back on after the frame is queued
        src = src.replace("            uart_write(out, (uint8_t)sp_frame(payload, len, out));\n",
                          "            uart_write(out, (uint8_t)sp_frame(payload, len, out));\n            sei();\n")
    (tmp_path / "main.c").write_text(src.replace(good, bad))
    elf = tmp_path / "broken.elf"
    subprocess.run(["avr-gcc", "-mmcu=atmega328p", "-DF_CPU=16000000UL", "-Os", "-std=c99", f"-I{FIRMWARE_DIR}",
                    str(tmp_path / "main.c"), str(FIRMWARE_DIR / "frame.c"), "-o", str(elf)], check=True)
    for name in checks:
        with pytest.raises(AssertionError):
            CHECKS[name](Tools(tools.harness, elf))


# --- the emulated firmware as the virtual phantom's board ------------------------------------------

def _signals(duration_s=2.0):
    """Synthetic transducer pressures on the 1 kHz grid: rest for 0.5 s, then smooth pushes of a
    few hundred Pa on the arms and an urethra ramp (the physics is the Python board's business)."""
    from softphantom.sensing.chain import default_chain
    from softphantom.virtual.board import BoardSignals

    t = np.arange(0.0, duration_s + 0.5 + 5e-4, 1e-3)
    bump = np.clip(np.sin(np.pi * np.clip((t - 0.5) / 1.2, 0, 1)) ** 2, 0, 1)
    p = np.column_stack([a * bump for a in (400.0, -300.0, 250.0, -150.0)] + [20e3 * bump])
    p += np.array([40.0, -60.0, 25.0, 0.0, 1500.0])          # transducer offsets
    chain = default_chain()
    return BoardSignals(t, p[:, :4], p, np.zeros(5), 0.0, np.full(4, 0.1), chain)


def _codes(sig, t):
    tr = sig.chain.transducers
    p = np.column_stack([np.interp(t, sig.t, sig.p_transducer[:, i]) for i in range(5)])
    return np.floor(1024 * np.column_stack([tr[i].ratio(p[:, i]) for i in range(5)]))


def test_firmware_board_gives_the_python_boards_frames(tools):
    """Same scenario, no noise: the firmware's sums equal the Python board's wherever the input is
    constant over the window, and elsewhere differ by at most N × the codes the input sweeps within
    the window (the Python board reads all N at the window's centre, the firmware at each
    conversion). Timing: the firmware's windows run 0.04 % long in simavr (its cycle timers fire
    at instruction ends) and start after its reset INFO and first conversion; both are bounded."""
    from softphantom.virtual.board import BoardConfig, VirtualBoard
    from softphantom.virtual.firmware_sim import FirmwareBoard

    sig = _signals()
    cfg = BoardConfig(osr=25, noise_codes=0.0)
    fb = FirmwareBoard(sig, cfg, elf=tools.elf, harness=tools.harness)
    data, t_fw = fb.frames(2.0)
    fb.close()
    frames = [f for f in StreamDecoder().feed(data) if isinstance(f, DataFrame)]
    assert len(frames) == len(t_fw) and frames[0].osr == 100 and frames[-1].osr == 25   # SET_OSR as acquire
    py = VirtualBoard(sig, cfg)
    n_same = 0
    for f in frames:
        py.osr = f.osr
        tc = f.t_us * 1e-6
        half = 5 * f.osr * 104e-6 / 2
        fw_raw = np.array(f.raw)
        py_raw = py.raw_at(np.array([tc]))[0]
        c = _codes(sig, np.linspace(tc - half - 2e-4, tc + half + 2e-4, 200))
        sweep = c.max(axis=0) - c.min(axis=0)
        assert np.all(np.abs(fw_raw - py_raw) <= f.osr * sweep), (f.seq, fw_raw - py_raw, sweep)
        if sweep.max() == 0:
            assert np.array_equal(fw_raw, py_raw)
            n_same += 1
    assert n_same >= 20
    t25 = np.array([f.t_us for f in frames if f.osr == 25]) * 1e-6
    period = np.median(np.diff(t25))
    assert abs(period / (1 / frame_rate_Hz(25)) - 1) < 1e-3
    assert 0 < t_fw[0] - 0.5 * 5 * 100 * 104e-6 < 1e-3    # the first window: 0.2-0.6 ms late


def test_firmware_board_on_a_pty_answers_the_host(tools):
    """`virtual serve --board firmware`: the host's SET_OSR reaches the emulated firmware, which
    switches to 19.2 Hz and answers with its own INFO."""
    import os
    import threading
    import time

    from softphantom.sensing.sources import SerialSource
    from softphantom.virtual.board import BoardConfig
    from softphantom.virtual.firmware_sim import FirmwareBoard
    from softphantom.virtual.serve import open_pty, serve_board

    sig = _signals(4.0)
    board = FirmwareBoard(sig, BoardConfig(osr=25), elf=tools.elf, harness=tools.harness)
    master, slave, path = open_pty()
    done = threading.Event()
    stats = {}
    th = threading.Thread(target=lambda: stats.update(serve_board(board, master, speed=2.0, stop=done.is_set)))
    th.start()
    src = SerialSource(path, sig.chain, osr=100)
    got = []
    t_end = time.monotonic() + 20.0
    try:
        while time.monotonic() < t_end and len(got) < 15:
            got += src.read(0.05) or []
    finally:
        src.close()
        done.set()
        th.join(5)
        board.close()
        os.close(master)
        os.close(slave)
    st = src.stats()
    assert st.firmware == "2.0.0" and stats["commands"] >= 1
    assert len(got) >= 15 and st.decoder.crc_errors == 0 and got[-1].osr == 100
    dt = np.diff([m.t_board for m in got if m.osr == 100])
    assert np.median(dt) == pytest.approx(1 / 19.23, rel=0.005)


def test_missing_simavr_is_one_line_naming_the_package(monkeypatch, tmp_path, capsys):
    from softphantom.cli import main
    from softphantom.virtual import firmware_sim

    monkeypatch.setattr(firmware_sim, "SIMAVR_HEADER", tmp_path / "no-such-header.h")
    with pytest.raises(firmware_sim.SimavrMissing, match="^simavr not installed: apt-get install simavr libsimavr-dev"):
        firmware_sim.build(tmp_path)
    code = main(["virtual", "run", "--scenario", "push-on-centre", "--model", str(tmp_path), "--out",
                 str(tmp_path / "o"), "--board", "firmware"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "libsimavr-dev" in err[0], err


def test_virtual_run_with_the_firmware_board(tools, coarse_model, coarse_truth_p1, tmp_path, monkeypatch):
    """`virtual run --board firmware` (its API): the recording comes from the emulated firmware's
    frames (its own INFO, SET_OSR to 25 as `acquire` sends it), tared and decoded as a board's,
    and follows the truth as the Python board's does."""
    import json

    from softphantom.sensing.recording import read_recording
    from softphantom.virtual import VirtualConfig, scenario_from_dict, simulate, write_run
    from softphantom.virtual import firmware_sim

    monkeypatch.setattr(firmware_sim, "build", lambda build_dir=None, n_channels=5, board="uno": (tools.harness, tools.elf))
    sc = scenario_from_dict({"name": "tiny-push", "duration_s": 2.0, "rest_s": 0.6,
                             "push": [{"point": "on-centre", "start_s": 0.7, "rise_s": 0.5, "hold_s": 0.2,
                                       "fall_s": 0.5, "force_N": [0.0, 2.0, 0.0]}]}, "tiny")
    cfg = VirtualConfig.seeded(seed=3, osr=25, order=1, board_kind="firmware")
    run = simulate(sc, coarse_model, cfg, truth_mesh=coarse_truth_p1)
    paths = write_run(run, tmp_path / "run")
    dec = StreamDecoder()
    fr = dec.feed(paths["frames"].read_bytes())
    assert isinstance(fr[0], InfoFrame) and fr[0].osr == 100                  # the reset INFO, N = 100
    assert isinstance(fr[1], InfoFrame) and fr[1].osr == 25                   # SET_OSR's answer
    assert [f.osr for f in fr[2:4]] == [100, 25]   # the first window had started at N = 100
    assert dec.stats.frames_lost == 0 and dec.stats.rejected == 0
    rec = read_recording(paths["recording"])
    board = json.loads(paths["meta"].read_text())["board"]
    assert board["kind"] == "firmware" and board["mcu"] == "uno"
    assert np.all(rec.osr[1:] == 25) and np.all(np.diff(rec.seq) == 1)
    from dataclasses import replace

    py = simulate(sc, coarse_model, replace(cfg, board_kind="python"), truth=run.truth)
    ms_fw, ms_py = list(run.source()), list(py.source())
    t_py = np.array([m.t for m in ms_py])
    dv_py = np.array([m.dV for m in ms_py])
    fw = [(m.t, m.dV) for m in ms_fw if m.osr == 25]
    err = np.array([dv - np.array([np.interp(t, t_py, dv_py[:, i]) for i in range(4)]) for t, dv in fw])
    # each board draws its own noise (σ 0.5 code a reading: 0.115 code a frame at N = 25, 0.16 for
    # the difference of two); one code of an arm's transducer is the bound
    from softphantom.sensing import P0_STANDARD_PA
    from softphantom.sensing.chain import MPXV7002
    from softphantom.sensing.pneumatics import boyle_dV

    code_Pa = 1000.0 / (1024 * MPXV7002.k1_per_kPa)
    bound = -boyle_dV(code_Pa, run.chain.v_total_m3, P0_STANDARD_PA)
    assert np.abs(dv_py).max() > 5 * bound.max()
    assert np.all(np.abs(err) < bound), (np.abs(err).max(axis=0) / bound)


def test_unknown_board_is_one_line(tmp_path, capsys):
    from softphantom.cli import main

    code = main(["virtual", "run", "--scenario", "push-on-centre", "--model", str(tmp_path), "--out",
                 str(tmp_path / "o"), "--board", "arduino"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--board" in err[0] and "python, firmware" in err[0], err


def test_the_firmware_built_for_six_channels_reads_six(tmp_path):
    # make N_CHANNELS=6: the same firmware reads A0..A5 round-robin and sends 6 sums a frame, its
    # INFO says 6, and a decoder made for 6 channels takes them (the frame period is 6·N·104 µs)
    why = simavr_missing()
    if why:
        pytest.skip(why)
    harness, elf = build(tmp_path, n_channels=6)
    codes = np.array([100, 300, 500, 700, 900, 1000])
    t, v = const_volts(codes)
    dec = StreamDecoder(6)
    frames = []
    with FirmwareSim(elf, harness=harness, n_channels=6) as sim:
        sim.set_voltages(t, v)
        frames += dec.feed(sim.run_until(0.001).data)  # its UART on (the chip drops what comes before)
        sim.send(encode_set_osr(10))
        frames += dec.feed(sim.run_until(0.2).data)  # the first window (N = 100) ends at 62 ms
    info = [f for f in frames if isinstance(f, InfoFrame)]
    data = [f for f in frames if isinstance(f, DataFrame) and f.osr == 10]
    assert info and all(f.n_channels == 6 for f in info)
    assert len(data) >= 3 and all(f.raw == tuple(int(c) * 10 for c in codes) for f in data[1:])
    dt = np.diff([f.t_us for f in data])
    assert np.allclose(dt, 6 * 10 * 104.0, rtol=CLOCK_TOLERANCE)


# --- the Arduino Mega 2560 (ATmega2560): up to 16 channels, ADC8..15 through MUX5 ----------------

def _distinct_codes(n: int) -> np.ndarray:
    """A code per channel, all different and none a multiple of another's bank twin (ch, ch ± 8)."""
    return np.array([37 + 61 * k for k in range(n)])


def check_mega_channels(harness: Path, elf: Path, n: int):
    """Each of the n inputs gets its own voltage; every DATA frame at N = 10 carries 10 × each
    channel's code on that channel (ADC8.. read through MUX5), its INFO says n, the conversions
    go round-robin 0..n-1, and a frame takes n·N·104 µs."""
    codes = _distinct_codes(n)
    t, v = const_volts(codes)
    dec = StreamDecoder(n)
    frames = []
    with FirmwareSim(elf, harness=harness, n_channels=n, board="mega", log_adc=True) as sim:
        sim.set_voltages(t, v)
        frames += dec.feed(sim.run_until(0.001).data)  # its UART on (the chip drops what comes before)
        sim.send(encode_set_osr(10))
        out = sim.run_until(n * 104e-6 * (100 + 5 * 10) + 0.005)  # the first window (N = 100), then 5 at N = 10
        frames += dec.feed(out.data)
    info = [f for f in frames if isinstance(f, InfoFrame)]
    data = [f for f in frames if isinstance(f, DataFrame) and f.osr == 10]
    assert info and all(f.n_channels == n for f in info)
    assert dec.stats.frames_lost == 0 and dec.stats.rejected == 0, dec.stats
    assert len(data) >= 3
    for f in data[1:]:  # the first at N = 10 may hold a conversion latched before the switch
        assert list(f.raw) == [int(c) * 10 for c in codes], (f.seq, np.array(f.raw) // 10 - codes)
    ch = out.adc["ch"].astype(int)
    assert np.array_equal(ch, (ch[0] + np.arange(len(ch))) % n)
    assert np.allclose(np.diff([f.t_us for f in data]), n * 10 * 104.0, rtol=CLOCK_TOLERANCE)


@pytest.fixture(scope="module")
def mega9(tmp_path_factory) -> Tools:
    why = simavr_missing()
    if why:
        pytest.skip(why)
    h, e = build(tmp_path_factory.mktemp("mega9"), n_channels=9, board="mega")
    return Tools(h, e)


def test_the_mega_firmware_reads_nine_channels_each_on_its_input(mega9):
    check_mega_channels(mega9.harness, mega9.elf, 9)


def test_the_mega_firmware_reads_sixteen_channels_each_on_its_input(tmp_path):
    why = simavr_missing()
    if why:
        pytest.skip(why)
    check_mega_channels(*build(tmp_path, n_channels=16, board="mega"), 16)


@pytest.mark.parametrize("good, bad", [
    # MUX5 never set: ADC8 is read as ADC0
    ("ADCSRB = (uint8_t)(ch_mux >= 8u ? _BV(MUX5) : 0u);", "ADCSRB = 0u;"),
    # MUX5 set for the channel converting now instead of the one latched next: ADC8 read as ADC0, ADC0 as ADC8
    ("ADCSRB = (uint8_t)(ch_mux >= 8u ? _BV(MUX5) : 0u);", "ADCSRB = (uint8_t)(ch_conv >= 8u ? _BV(MUX5) : 0u);"),
    # the UNO's mux code on the Mega: channel 8 is MUX3 (a differential input), not ADC8
    ("ADMUX = (uint8_t)(_BV(REFS0) | (ch_mux & 7u));", "ADMUX = (uint8_t)(_BV(REFS0) | ch_mux);"),
])
def test_a_mega_firmware_with_a_broken_channel_select_fails(mega9, tmp_path, good, bad):
    src = (FIRMWARE_DIR / "main.c").read_text()
    assert src.count(good) == 1, f"main.c no longer has {good!r}: update the mutant"
    (tmp_path / "main.c").write_text(src.replace(good, bad))
    elf = tmp_path / "broken.elf"
    subprocess.run(["avr-gcc", "-mmcu=atmega2560", "-DF_CPU=16000000UL", "-DSP_N_CHANNELS=9u", "-Os", "-std=c99",
                    f"-I{FIRMWARE_DIR}", str(tmp_path / "main.c"), str(FIRMWARE_DIR / "frame.c"), "-o", str(elf)],
                   check=True)
    with pytest.raises(AssertionError):
        check_mega_channels(mega9.harness, elf, 9)


def test_the_harness_refuses_a_firmware_built_for_the_other_mcu(mega9, tools):
    r = subprocess.run([str(mega9.harness), str(tools.elf)], input=b"Q", capture_output=True)
    err = r.stderr.decode().strip().splitlines()
    assert r.returncode == 2 and err == [
        "fw_sim: the firmware is built for avr5, this harness runs atmega2560 (avr6): build both with the same make BOARD="]


def _arm_signals(n_arms: int, duration_s=1.0):
    """Constant, distinct transducer pressures for a board of n_arms + 1 channels (MPXV7002 arms
    from -1.5 kPa up, an MPX4250D urethra at 30 kPa)."""
    from softphantom.sensing.chain import default_chain
    from softphantom.virtual.board import BoardSignals

    t = np.arange(0.0, duration_s + 0.5 + 5e-4, 1e-3)
    p_arms = -1500.0 + 250.0 * np.arange(n_arms)
    p = np.tile(np.r_[p_arms, 30e3], (len(t), 1))
    chain = default_chain([500e-9] * n_arms, layout=ChannelLayout(tuple(f"arm{k}" for k in range(n_arms)), (), ("urethra",)))
    return BoardSignals(t, p[:, :n_arms], p, np.zeros(n_arms + 1), 0.0, np.full(n_arms, 0.1), chain)


def test_the_virtual_board_on_the_mega_reads_eight_arms(mega9):
    """`virtual run --board firmware --mcu mega` for a design of 8 arms: the emulated Mega's frames
    carry N × each transducer's code, floor(1024 · ratio(p)), on its channel (the datasheet
    transfer functions as the independent truth)."""
    from softphantom.virtual.board import BoardConfig
    from softphantom.virtual.firmware_sim import FirmwareBoard

    sig = _arm_signals(8)
    tr = sig.chain.transducers
    codes = np.floor([1024 * tr[i].ratio(sig.p_transducer[0, i]) for i in range(9)]).astype(int)
    assert len(set(codes)) == 9
    fb = FirmwareBoard(sig, BoardConfig(osr=25, noise_codes=0.0, mcu="mega"), elf=mega9.elf, harness=mega9.harness)
    data, t_fw = fb.frames(0.3)
    fb.close()
    frames = [f for f in StreamDecoder(9).feed(data) if isinstance(f, DataFrame)]
    assert len(frames) == len(t_fw) and frames[-1].osr == 25
    at25 = [f for f in frames if f.osr == 25][1:]
    assert len(at25) >= 5 and all(list(f.raw) == list(25 * codes) for f in at25)
    assert fb.rate_Hz == pytest.approx(1 / (9 * 25 * 104e-6))


def test_a_board_with_too_few_inputs_is_refused_in_one_line(monkeypatch, tmp_path, capsys):
    from types import SimpleNamespace

    from softphantom import design
    from softphantom.cli import main
    from softphantom.errors import UserError
    from softphantom.virtual import firmware_sim
    from softphantom.virtual.board import BoardConfig
    from softphantom.virtual.firmware_sim import FirmwareBoard

    with pytest.raises(UserError, match=r"^--mcu uno: the Arduino UNO has 6 analog inputs \(A0-A5\), the design "
                                        r"needs 9 channels \(8 arms and the urethra\); --mcu mega has 16$"):
        FirmwareBoard(_arm_signals(8), BoardConfig(mcu="uno"))
    with pytest.raises(UserError, match=r"^--mcu mega: the Arduino Mega 2560 has 16 analog inputs \(A0-A15\), the "
                                        r"design needs 17 channels \(16 arms and the urethra\)$"):
        firmware_sim.check_board("mega", 17)
    # the CLI: a design of 6 arms on the UNO, refused before the truth's solve
    monkeypatch.setattr(firmware_sim, "simavr_missing", lambda: None)
    monkeypatch.setattr(design, "load_model",
                        lambda d: SimpleNamespace(design=SimpleNamespace(arm_names=tuple("abcdef"))))
    args = ["virtual", "run", "--scenario", "push-on-centre", "--model", str(tmp_path), "--out", str(tmp_path / "o"),
            "--board", "firmware"]
    for extra, words in (([], ["--mcu uno", "the Arduino UNO has 6 analog inputs", "7 channels", "--mcu mega"]),
                         (["--mcu", "due"], ["--mcu", "uno, mega", "'due'"])):
        code = main(args + extra)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and all(w in err[0] for w in words), err
