"""Acquisition: a fake board on a pty pair and on loop://, the serial source (resync, counts,
silence, reconnect), the crash-safe recording (kill -9, truncation), replay, and the CLI."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import tty
import warnings
from pathlib import Path

import numpy as np
import pytest
import serial

from softphantom.cli import main
from softphantom.records import ARM_NAMES
from softphantom.errors import FileFormatError, UserError
from softphantom.sensing.chain import default_chain, nominal_tare, pa_to_counts, tare_from_window, MPXV7002
from softphantom.sensing.protocol import (
    CMD_GET_INFO,
    CMD_SET_OSR,
    FrameError,
    decode_body,
    encode_data,
    encode_info,
)
from softphantom.sensing.recording import (
    COLUMNS,
    Recorder,
    TruncatedRecordingWarning,
    read_recording,
    retare,
)
from softphantom.sensing.sources import FrameSource, ReplaySource, SerialSource
sys.path.insert(0, str(Path(__file__).resolve().parent))
from subproc import sigint_default  # noqa: E402

REST = [51150, 51150, 51150, 51150, 4046]


def _raw(k, push_Pa=0.0):
    """Raw sums at frame k: arms at rest ± 2 codes of noise, front_zpos pushed by push_Pa."""
    r = np.array(REST) + (np.arange(5) + k) % 3 - 1
    r[0] = int(pa_to_counts(push_Pa, MPXV7002, 100)) + (k % 3) - 1
    return [int(x) for x in r]


class FakeBoard:
    """Writes a script of byte chunks to a pty master from a thread, reads the host's commands."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)                 # no echo, no CR/LF translation before pyserial opens it
        self.path = os.ttyname(self.slave)
        self.commands = []
        self.sent_at = {}                      # seq -> monotonic time written
        self._stop = threading.Event()
        self._dec_buf = b""
        self._last_t_us = 0

    def run(self, script):
        def go():
            for item in script:
                if self._stop.is_set():
                    return
                if isinstance(item, float):
                    time.sleep(item)
                    continue
                if item == "connected":              # wait for the host's first command (it opened the port)
                    while not self.commands and not self._stop.is_set():
                        time.sleep(0.01)
                        self._poll_commands()
                    continue
                seq, data = item
                os.write(self.master, data)
                try:
                    self._last_t_us = decode_body(data.strip(b"\x00")).t_us
                except FrameError:                   # the script's deliberately bad frames
                    pass
                if seq is not None:
                    self.sent_at[seq] = time.monotonic()
                self._poll_commands()
        self.thread = threading.Thread(target=go, daemon=True)
        self.thread.start()
        return self

    def _poll_commands(self):
        import select
        while select.select([self.master], [], [], 0)[0]:
            self._dec_buf += os.read(self.master, 256)
        *bodies, self._dec_buf = self._dec_buf.split(b"\x00")
        for b in bodies:
            if b:
                cmd = decode_body(b)
                self.commands.append(cmd)
                # like the firmware: answer GET_INFO and SET_OSR with an INFO frame
                os.write(self.master, encode_info(0, self._last_t_us, (1, 0, 0), 5, cmd.osr or 100))

    def close(self):
        self._stop.set()
        if hasattr(self, "thread"):
            self.thread.join(5)
        os.close(self.master)
        os.close(self.slave)


def _stream(seqs, dt=0.01, push=lambda k: 0.0):
    """Frames paced at dt (board clock advancing by dt per frame, as the real board's does)."""
    out = []
    for k in seqs:
        out += [(k, encode_data(k & 0xFFFF, int(round(k * dt * 1e6)), 100, _raw(k, push(k)))), dt]
    return out


def test_pty_board_garbage_corruption_truncation_pause():
    board = FakeBoard()
    good = _stream(range(1, 20))
    bad = bytearray(encode_data(20, 200_000, 100, _raw(20))); bad[16] ^= 0x40
    script = ([(None, encode_info(0, 0, (1, 0, 0), 5, 100))] + good
              + [(None, b"\xde\xad\xbe\xef garbage \x17\x00")]            # 1 malformed
              + [(20, bytes(bad))]                                        # 1 CRC error
              + [(21, encode_data(21, 210_000, 100, _raw(21))[:20])]  # truncated: 22's 0x00 ends it
              + _stream(range(22, 30))
              + [0.9]                                                     # the board goes quiet
              + _stream(range(30, 40)))
    src = SerialSource(board.path, default_chain(), osr=100, silence_s=0.5)
    got, states, silent_at = [], [], None
    try:
        src.read(0.01)                        # open the port first: opening flushes its input
        board.run(script)
        t_end = time.monotonic() + 60  # a deadline, not a speed: the loop ends at frame 39
        rx_at = {}
        while time.monotonic() < t_end and (not got or got[-1].seq != 39):
            new = src.read(0.02)                                          # never raises
            got += new
            rx_at.update((m.seq, time.monotonic()) for m in new)
            st = src.stats()
            if st.state == "silent" and silent_at is None:
                silent_at = time.monotonic()
            states.append(st.state)
        s = src.stats()
    finally:
        src.close()
        board.close()
    seqs = [m.seq for m in got]
    assert seqs == list(range(1, 20)) + list(range(22, 40))      # the truncated 21 costs only itself
    d = s.decoder
    # INFO: the board's own, its answers to GET_INFO and SET_OSR on connecting, and to the
    # GET_INFO the host sends when the board falls silent
    assert d.frames_ok == 37 and d.info_frames == 4
    assert d.crc_errors >= 1 and d.crc_errors + d.malformed == 3         # flipped, noise, 21's head
    assert (d.seq_gaps, d.frames_lost) == (1, 2)                          # 20, 21
    assert s.silent_events == 1 and s.state == "ok" and s.firmware == "1.0.0"
    # detected during the 0.9 s pause (after the host got frame 29, before it got frame 30), and
    # not before 0.5 s of silence; how soon within the pause is scheduling, not a property
    assert rx_at[29] < silent_at < rx_at[30]
    assert silent_at - board.sent_at[29] >= 0.5
    assert all(m.status == "ok" for m in got)
    # the host asked for the board's info and set N on connecting
    assert {c.kind for c in board.commands} >= {CMD_GET_INFO, CMD_SET_OSR}
    assert [c.osr for c in board.commands if c.kind == CMD_SET_OSR] == [100]
    # host times follow the board clock (10 ms a frame), free of the reads' jitter: the offset
    # follows the fastest frame and may rise by at most CLOCK_DRIFT (0.5 %) of board time
    dt = np.diff([m.t for m in got[:19]])
    assert np.all(dt >= 0) and np.all(dt[2:] <= 0.010 * 1.005 + 1e-9)
    assert np.median(dt) == pytest.approx(0.010, rel=0.006)


def test_unplug_and_reconnect_on_loop_ports():
    """The port dies (USB unplugged), opening fails twice, then the board is back."""
    ports = []

    def opener(url, **kw):
        n = len(ports)
        if n in (1, 2):
            ports.append(None)
            raise serial.SerialException("no such device")
        p = serial.serial_for_url("loop://", **kw)
        base = 0 if n == 0 else 100
        p.write(b"".join(encode_data(base + k, 52_000 * (base + k), 100, _raw(k)) for k in range(5)))
        ports.append(p)
        return p

    src = SerialSource("fake", default_chain(), opener=opener, reconnect_every_s=0.01)
    got, states = [], []
    for _ in range(200):
        got += src.read(0.01)
        states.append(src.stats().state)
        if len(got) == 5 and ports[0].is_open:
            ports[0].close()                                     # unplug
        if len(got) == 10:
            break
    s = src.stats()
    src.close()
    assert [m.seq for m in got] == [0, 1, 2, 3, 4, 100, 101, 102, 103, 104]
    assert "disconnected" in states and s.reconnects == 1 and s.state == "ok"
    assert s.decoder.frames_ok == 10
    assert s.decoder.malformed == 2      # our own GET_INFO echoed by each loop:// port


def test_frame_source_for_simulators_and_bad_input():
    chain = default_chain()
    chunks = [encode_data(k, 52_000 * k, 25, [int(x / 4) for x in _raw(k, 500.0)]) for k in range(4)]
    chunks.insert(2, b"\x00\xff\x00\x01\x02\x03\x00")            # garbage between frames
    ms = list(FrameSource(chunks, chain, nominal_tare(chain)))
    assert [m.seq for m in ms] == [0, 1, 2, 3]
    assert ms[0].dp[0] == pytest.approx(500.0, abs=25) and ms[0].dV[0] < 0
    assert ms[0].osr == 25


# ------------------------------------------------------------------ recording
def _measurements(n, chain=None):
    chain = chain or default_chain()
    src = FrameSource([encode_data(k, 52_000 * k, 100, _raw(k, 300.0 * np.sin(k / 5))) for k in range(n)], chain)
    return list(src)


def test_recording_round_trip_truncation_and_errors(tmp_path):
    chain = default_chain()
    path = tmp_path / "rec.csv"
    ms = _measurements(30, chain)
    meta = {"chain": chain.summary(), "tare": nominal_tare(chain).to_dict(), "osr": 100}
    with Recorder(path, meta, layout=chain.layout) as rec:
        for m in ms:
            rec.write(m)
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# {") and lines[1] == ",".join(COLUMNS)
    assert "dp_front_zpos_kPa" in COLUMNS and "dV_back_xneg_mm3" in COLUMNS and "raw_urethra" in COLUMNS
    back = read_recording(path)
    assert len(back) == 30 and not back.truncated
    assert np.array_equal(back.raw, np.array([m.raw for m in ms]))
    assert np.allclose(back.dp, [m.dp for m in ms], atol=1e-3)           # stored in kPa to 1e-6
    assert np.allclose(back.dV, [m.dV for m in ms], atol=1e-15)          # mm³ to 1e-6
    # cut in the middle of the last row: 29 rows and a warning
    data = path.read_bytes()
    cut = tmp_path / "cut.csv"
    cut.write_bytes(data[: len(data) - 20])
    with pytest.warns(TruncatedRecordingWarning, match="incomplete"):
        short = read_recording(cut)
    assert len(short) == 29 and short.truncated
    # a damaged row in the middle is an error naming its line
    bad = tmp_path / "bad.csv"
    lines[10] = lines[10].replace(",", ";", 3)
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(FileFormatError, match="line 11"):
        read_recording(bad)
    (tmp_path / "nometa.csv").write_text("t_s,seq\n")
    with pytest.raises(FileFormatError, match="line 1"):
        read_recording(tmp_path / "nometa.csv")
    with pytest.raises(UserError, match="never overwritten"):
        Recorder(path, meta, layout=chain.layout)


def test_retare_from_raw_and_replay(tmp_path):
    chain = default_chain()
    path = tmp_path / "rec.csv"
    with Recorder(path, {"chain": chain.summary()}, layout=chain.layout) as rec:
        for m in _measurements(20, chain):
            rec.write(m)
    back = read_recording(path)
    shifted = nominal_tare(chain)
    off = shifted.offset_codes.copy(); off[0] += 2.048                   # +10 Pa of offset
    re = retare(back, type(shifted)(off, shifted.p0_Pa))
    assert np.allclose(re.dp[:, 0], back.dp[:, 0] - 10.0, atol=1e-3)
    assert re.meta["tare"]["offset_codes"][0] == pytest.approx(off[0])
    replayed = list(ReplaySource(path))
    assert [m.seq for m in replayed] == list(range(20))
    assert np.allclose([m.dp for m in replayed], back.dp)


# ------------------------------------------------------------------ the CLI and kill -9
def _board_forever(board, n=2000, push=lambda k: 0.0):
    script = [(None, encode_info(0, 0, (1, 0, 0), 5, 100))] + _stream(range(1, n), dt=0.02, push=push)
    return board.run(script)


def test_cli_acquire_records_with_tare_and_metadata(tmp_path, capsys):
    board = FakeBoard()
    out = tmp_path / "a.csv"
    try:
        _board_forever(board, 200)
        # 2 s at the board's 50 Hz: ~100 frames on an idle host, ≥ 30 even when the fake board's
        # thread gets a fraction of a core (0.8 s gave 25 at load average 30)
        rc = main(["acquire", "--port", board.path, "--out", str(out), "--duration-s", "2.0",
                   "--tare-s", "0.3", "--p0-kPa", "95"])
    finally:
        board.close()
    assert rc == 0, capsys.readouterr()
    rec = read_recording(out)
    assert len(rec) >= 30
    assert rec.meta["firmware"] == "1.0.0" and rec.meta["protocol_version"] == 2
    assert rec.meta["p0_Pa"] == 95_000 and rec.meta["tare"]["n_samples"] >= 5
    assert np.all(np.abs(rec.dp) < 15)                                  # tared at rest
    assert np.all(np.diff(rec.seq) == 1)


def test_cli_acquire_refuses_a_tare_window_not_at_rest(tmp_path, capsys):
    board = FakeBoard()
    out = tmp_path / "b.csv"
    try:
        _board_forever(board, 200, push=lambda k: 40.0 * k)              # a steady push: 2 kPa/s
        rc = main(["acquire", "--port", board.path, "--out", str(out), "--duration-s", "0.5", "--tare-s", "0.3"])
    finally:
        board.close()
    assert rc == 2
    assert "front_zpos" in capsys.readouterr().err and not out.exists()


def _acquire_until(board, out, lines: int, **popen) -> subprocess.Popen:
    """An ``acquire`` process recording ``board`` (streaming) into ``out``, once ``out`` holds ``lines``
    lines (or 60 s passed)."""
    _board_forever(board, 5000)
    proc = subprocess.Popen([sys.executable, "-m", "softphantom", "acquire", "--port", board.path,
                             "--out", str(out), "--tare-s", "0.2"], **popen)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not out.exists() or out.read_bytes().count(b"\n") < lines):
        time.sleep(0.05)
    return proc


def test_kill_9_of_a_recording_process_reads_back(tmp_path):
    board = FakeBoard()
    out = tmp_path / "k.csv"
    proc = None
    try:
        proc = _acquire_until(board, out, 40, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TruncatedRecordingWarning)
            seen = read_recording(out)                                   # what a reader saw before the kill
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc and proc.poll() is None:
            proc.kill()
        board.close()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TruncatedRecordingWarning)       # a cut row is allowed
        rec = read_recording(out)
    assert len(rec) >= 38                                             # 40 lines = metadata + header + 38 rows
    assert np.all(np.diff(rec.seq) == 1)
    # every row already in the file before the kill is still there, unchanged (a loaded machine
    # changes how many, not whether they survive)
    assert len(seen) >= 38 and len(rec) >= len(seen)                      # a cut row is not read
    np.testing.assert_array_equal(rec.seq[:len(seen)], seen.seq)


def test_ctrl_c_stops_acquire_cleanly(tmp_path):
    board = FakeBoard()
    out = tmp_path / "c.csv"
    proc = None
    try:
        proc = _acquire_until(board, out, 20, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              preexec_fn=sigint_default)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc and proc.poll() is None:
            proc.kill()
        board.close()
    assert proc.returncode == 130, stderr            # Ctrl-C: the shell's code, so make stops
    assert "Traceback" not in stderr and "stopped" in stderr and "wrote" in stdout
    rec = read_recording(out)                       # complete: no truncation warning
    assert not rec.truncated and len(rec) >= 18     # 20 lines = metadata + header + 18 rows


def test_cli_acquire_after_a_board_freeze_reads_back(tmp_path, capsys):
    """The board freezes for 1 s (as SIGSTOP of ``virtual serve``), then sends that second's frames
    at once: the silent marker must not put the file out of time order."""
    board = FakeBoard()
    out = tmp_path / "frozen.csv"
    dt = 0.01
    script = ["connected", (None, encode_info(0, 0, (1, 0, 0), 5, 100))] + _stream(range(1, 60), dt=dt)
    script += [1.0] + [(k, encode_data(k, int(round(k * dt * 1e6)), 100, _raw(k))) for k in range(60, 160)]
    script += _stream(range(160, 400), dt=dt)
    try:
        board.run(script)
        rc = main(["acquire", "--port", board.path, "--out", str(out), "--duration-s", "2.0", "--tare-s", "0.2"])
    finally:
        board.close()
    assert rc == 0, capsys.readouterr()
    rec = read_recording(out)
    assert "silent" in [e.kind for e in rec.events]
    assert len(rec) >= 150 and np.all(np.diff(rec.seq) == 1)
    t = np.array([float(line.split(",")[0]) for line in out.read_text().splitlines()[2:]])
    assert np.all(np.diff(t) >= 0)                                 # marker rows included


@pytest.mark.parametrize("args, option", [(["--tare-s", "-1"], "--tare-s"), (["--tare-s", "nan"], "--tare-s"),
                                          (["--connect-timeout-s", "-1"], "--connect-timeout-s"),
                                          (["--on-new-board", "ignore"], "--on-new-board")])
def test_cli_acquire_checks_its_options_before_the_port(tmp_path, capsys, args, option):
    t0 = time.monotonic()
    rc = main(["acquire", "--port", "/dev/nonexistent", "--out", str(tmp_path / "x.csv"), *args])
    err = capsys.readouterr().err
    assert rc == 2 and option in err and "nonexistent" not in err, err
    assert len(err.strip().splitlines()) == 1 and time.monotonic() - t0 < 3.0      # no wait for the port
    assert not (tmp_path / "x.csv").exists()


def test_acquire_status_row_agrees_with_the_state():
    import io

    from rich.console import Console

    from softphantom.cli.sensing import _status_table
    from softphantom.sensing.protocol import DecoderStats
    from softphantom.sensing.sources import SourceStats

    m = next(iter(FrameSource([encode_data(1, 0, 100, REST)], default_chain())))
    assert m.status == "ok"

    def rows(state):
        con = Console(file=io.StringIO(), width=160)
        con.print(_status_table(SourceStats(state, DecoderStats(), last=m), 3.0, 10, Path("a.csv"), ARM_NAMES))
        text = con.file.getvalue()
        return {ln.split()[1]: " ".join(ln.split()[2:]) for ln in text.splitlines() if ln.split()[1:2]}

    assert rows("ok")["status"].strip("│ ") == "ok"
    for state in ("disconnected", "silent"):
        got = rows(state)
        assert state in got["state"] and state in got["status"] and not got["status"].strip("│ ") == "ok", got
