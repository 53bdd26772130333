"""The virtual board on a pseudo-terminal, so ``softphantom acquire --port /dev/pts/N`` and
``softphantom estimate --source serial:/dev/pts/N`` see a board.

The pty is raw (no line discipline), frames go out in real time (times ``speed``), and the board
answers the host's commands as the firmware does: GET_INFO → INFO, SET_OSR → new OSR, then INFO.
After the scenario the board keeps streaming the rest state (a real board does not stop) unless
``once``. Writes never block: with nobody reading, the pty's buffer fills and frames are dropped,
as a UART without a listener drops them.
"""

from __future__ import annotations

import os
import select
import time
import tty
from collections.abc import Callable

from softphantom.sensing.protocol import CMD_GET_INFO, CMD_SET_OSR, Command, FrameError, decode_body
from softphantom.virtual.board import VirtualBoard

TICK_S = 0.01


def open_pty() -> tuple[int, int, str]:
    """(master fd, slave fd, slave path) of a new raw pty; the master is non-blocking."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


def _commands(buf: bytearray) -> list[Command]:
    out = []
    while (end := buf.find(0)) >= 0:
        body = bytes(buf[:end])
        del buf[: end + 1]
        if not body:
            continue
        try:
            f = decode_body(body)
        except FrameError:
            continue
        if isinstance(f, Command):
            out.append(f)
    if len(buf) > 256:
        buf.clear()
    return out


def serve_board(board: VirtualBoard, master: int, *, speed: float = 1.0, once: bool = False,
                stop: Callable[[], bool] | None = None, on_tick: Callable[[float, int], None] | None = None) -> dict:
    """Stream ``board``'s frames to the pty ``master`` in real time; returns counters."""
    t0 = time.monotonic()
    sent = dropped = commands = 0
    inbox = bytearray()
    pending = board.info()
    while True:
        now = (time.monotonic() - t0) * speed
        if once and now > board.duration_s:
            break
        if stop is not None and stop():
            break
        data, _ = board.frames(now)
        pending += data
        if pending:
            try:
                n = os.write(master, pending)
                sent += n
                pending = pending[n:]
            except BlockingIOError:
                dropped += len(pending)
                pending = b""
            except OSError:
                break
            if len(pending) > 4096:  # nobody reads: drop, as a UART would
                dropped += len(pending)
                pending = b""
        r, _, _ = select.select([master], [], [], TICK_S)
        if r:
            try:
                got = os.read(master, 4096)
            except (BlockingIOError, OSError):
                got = b""
            inbox += got
            receive = getattr(board, "receive", None)  # an emulated firmware reads the bytes itself
            if receive is not None:
                receive(got)
            for c in _commands(inbox):
                commands += 1
                if receive is not None:
                    continue
                if c.kind == CMD_SET_OSR and c.osr:
                    board.set_osr(c.osr)
                if c.kind in (CMD_SET_OSR, CMD_GET_INFO):
                    pending += board.info()
        if on_tick is not None:
            on_tick(now, board.seq)
    return {"bytes_sent": sent, "bytes_dropped": dropped, "frames": board.seq, "commands": commands}
