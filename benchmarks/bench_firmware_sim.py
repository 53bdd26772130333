"""The board's firmware in simavr: its speed against real time, and its frames against the Python board's.

    .venv/bin/python benchmarks/bench_firmware_sim.py [--seconds 20] [--session-s 60] [--core 0]

(a) Speed: the emulated board (firmware/sim/fw_sim, the firmware's .elf, the ADC fed from a 1 kHz
voltage grid with 0.5 code of noise) runs ``--seconds`` of board time at N = 25 and N = 100,
pinned to one core; the harness's own CPU time (getrusage of the child) and the wall time give
the speed in multiples of real time. ``softphantom virtual --board firmware`` needs at least 1.
(b) Agreement: a ``--session-s`` session of smooth pushes (synthetic transducer pressures, no
noise) through the emulated firmware (``FirmwareBoard``) and through the Python board
(``VirtualBoard``), each frame of the firmware compared with the Python board's frame at the same
window centre: the largest difference in mean code per reading, in Pa at an arm's MPXV7002, and
the frame schedules' offset at the start and at the end of the session.
"""

from __future__ import annotations

import argparse
import os
import resource
import time

import numpy as np

from _results import write_table
from softphantom.sensing.board import frame_rate_Hz
from softphantom.sensing.chain import MPXV7002, default_chain
from softphantom.sensing.protocol import DataFrame, StreamDecoder, encode_set_osr
from softphantom.virtual.board import BoardConfig, BoardSignals, VirtualBoard
from softphantom.virtual.firmware_sim import VS_V, FirmwareBoard, FirmwareSim, build


def speed(osr: int, seconds: float) -> dict:
    t = np.arange(0.0, seconds + 0.5, 1e-3)
    v = VS_V * (0.5 + 0.05 * np.sin(2 * np.pi * 0.5 * t[:, None] + np.arange(5)))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    w0 = time.perf_counter()
    with FirmwareSim(noise_codes=0.5, seed=1) as sim:
        sim.set_voltages(t, v)
        sim.run_until(0.002)
        sim.send(encode_set_osr(osr))
        dec = StreamDecoder()
        n = 0
        for k in range(1, int(seconds * 10) + 1):       # 0.1 s steps, as `virtual serve` asks
            n += sum(isinstance(f, DataFrame) for f in dec.feed(sim.run_until(k * 0.1).data))
    wall = time.perf_counter() - w0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"osr": osr, "frames": n, "cpu_s": cpu, "wall_s": wall, "x_cpu": seconds / cpu, "x_wall": seconds / wall,
            "lost": dec.stats.frames_lost}


def session_signals(duration_s: float) -> BoardSignals:
    """Rest, then a smooth push every 4 s on the arms (±400 Pa) and the urethra (20 kPa)."""
    t = np.arange(0.0, duration_s + 0.5 + 5e-4, 1e-3)
    phase = np.clip((t - 1.0) % 4.0 / 3.0, 0, 1) * (t > 1.0)
    bump = np.sin(np.pi * phase) ** 2
    p = np.column_stack([a * bump for a in (400.0, -300.0, 250.0, -150.0)] + [20e3 * bump])
    p += np.array([40.0, -60.0, 25.0, 0.0, 1500.0])
    return BoardSignals(t, p[:, :4], p, np.zeros(5), 0.0, np.full(4, 0.1), default_chain())


def agreement(duration_s: float, osr: int = 25) -> dict:
    sig = session_signals(duration_s)
    cfg = BoardConfig(osr=osr, noise_codes=0.0)
    fb = FirmwareBoard(sig, cfg)
    data = bytearray()
    for k in range(1, int(duration_s * 10) + 1):
        data += fb.frames(k * 0.1)[0]
    fb.close()
    frames = [f for f in StreamDecoder().feed(bytes(data)) if isinstance(f, DataFrame) and f.osr == osr]
    py = VirtualBoard(sig, cfg)
    t = np.array([f.t_us for f in frames]) * 1e-6
    fw = np.array([f.raw for f in frames], float) / osr
    pb = py.raw_at(t) / osr
    d = np.abs(fw - pb)
    period = 1 / frame_rate_Hz(osr)
    # the Python board's window centres are (k + 0.5)·period from 0; the firmware's from its own start
    k0 = np.round((t[0] - period / 2) / period)
    off_start = t[0] - (k0 + 0.5) * period
    off_end = t[-1] - (k0 + len(t) - 1 + 0.5) * period
    code_Pa = 1000.0 / (1024 * MPXV7002.k1_per_kPa)
    return {"frames": len(frames), "max_code": d.max(), "rms_code": np.sqrt((d ** 2).mean()),
            "max_Pa": d[:, :4].max() * code_Pa, "off_start_ms": off_start * 1e3, "off_end_ms": off_end * 1e3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="board time per speed run (s)")
    ap.add_argument("--session-s", type=float, default=60.0, help="length of the agreement session (s)")
    ap.add_argument("--core", type=int, default=0, help="the one core the emulator runs on")
    a = ap.parse_args()
    build()
    os.sched_setaffinity(0, {a.core})        # the harness inherits it
    rows = []
    for osr in (25, 100):
        r = speed(osr, a.seconds)
        print(r)
        rows.append([f"speed, N = {osr} ({frame_rate_Hz(osr):.1f} Hz)",
                     f"{a.seconds:g} s of board time: {r['cpu_s']:.2f} CPU-s, {r['wall_s']:.2f} s wall",
                     f"**{r['x_cpu']:.1f}×** real time (CPU), {r['x_wall']:.1f}× (wall); {r['frames']} frames, "
                     f"{r['lost']} lost"])
    g = agreement(a.session_s)
    print(g)
    rows.append([f"agreement with the Python board, N = 25, {a.session_s:g} s session",
                 f"{g['frames']} frames, no noise",
                 f"mean code per reading within {g['max_code']:.2f} (RMS {g['rms_code']:.3f}); "
                 f"≤ {g['max_Pa']:.1f} Pa at an arm"])
    rows.append(["frame schedule against the Python board's", "window centres",
                 f"{g['off_start_ms']:+.2f} ms at the start, {g['off_end_ms']:+.2f} ms after {a.session_s:g} s"])
    write_table("firmware_sim", ["", "run", "result"], rows,
                caption="The firmware in simavr (`softphantom virtual --board firmware`): speed on one core "
                        "and agreement with the Python board.")


if __name__ == "__main__":
    main()
