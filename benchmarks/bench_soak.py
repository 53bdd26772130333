"""Soak of ``estimate`` on a 77 Hz board: nothing skipped that is not counted and
explained, memory flat.

    .venv/bin/python benchmarks/bench_soak.py [--duration-s 300] [--estimator atlas --estimator refresh]
                                              [--model DIR] [--load 2] [--peer-s 0]

A writer thread plays a board at N = 25 (76.9 Hz, protocol v2, real time, the board clock in the
frames) onto a pty; the host side is the real path: ``softphantom.sources.open_source("serial:…")``
(tare on the first second at rest) → ``estimate_stream`` with each estimator (``--estimator``:
atlas, the default of ``estimate``, and the async refresh one; both by default) → the estimate
CSV. ``--load`` busy processes run alongside (the machine's two cores busy, as in the issue's
soak). Reported per estimator: frames sent / received / estimated / skipped (with the reason:
lagging more than ``MAX_LAG_S``), decoder losses, link events, resident memory (VmRSS) sampled
every second and the growth of its baseline after the warm-up (:func:`memory_growth`: MB/h and
% of the memory per hour). ``--peer-s``: also the latest-sample slot (every sample but the newest of a read dropped),
i.e. the same queue with ``MAX_LAG_S`` = 0, for comparison.
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import os
import subprocess
import sys
import tempfile
import threading
import time
import tty

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from _results import add_results_option, grouped, write_table  # noqa: E402

import softphantom.estimation.stream as stream_mod  # noqa: E402
from softphantom.progress import message_handler  # noqa: E402
from softphantom.design import BIPDesign, build_model, load_model  # noqa: E402
from softphantom.estimation import EstimatorConfig, estimate_stream, open_estimator  # noqa: E402
from softphantom.sources import open_source  # noqa: E402
from softphantom.sensing.board import frame_rate_Hz  # noqa: E402
from softphantom.sensing.chain import MPXV7002, pa_to_counts  # noqa: E402
from softphantom.sensing.protocol import encode_data, encode_info  # noqa: E402

OSR = 25


def rss_MB() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def board_process(master: int, stop, sent) -> None:
    """Frames at the board's 77 Hz in real time on a pty, in its own process (a real board does
    not share the host's interpreter): 1.5 s at rest, then a slow push (±300 Pa at the back arms,
    0.2 Hz) with ADC noise."""
    rng = np.random.default_rng(0)
    dt = 1.0 / frame_rate_Hz(OSR)
    t0 = time.monotonic()
    os.write(master, encode_info(0, 0, (2, 0, 0), 5, OSR))
    rest = np.array([pa_to_counts(0.0, MPXV7002, OSR)] * 4 + [OSR * 40.46])
    k = 0
    while not stop.is_set():
        t = k * dt
        wait = t0 + t - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        p = 0.0 if t < 1.5 else 300.0 * np.sin(2 * np.pi * 0.2 * (t - 1.5))
        raw = rest + np.array([0, 0, 1, 1, 0]) * p * OSR * 1024 * MPXV7002.k1_per_kPa / 1000.0
        raw = np.round(raw + rng.normal(0, 0.5 * np.sqrt(OSR), 5)).astype(int)
        try:
            os.write(master, encode_data(k & 0xFFFF, int(t * 1e6) & 0xFFFFFFFF, OSR, raw))
        except OSError:
            return
        k += 1
        sent.value = k


def soak(model, duration_s: float, label: str, kind: str = "atlas", cache_dir=None) -> dict:
    master, slave = os.openpty()
    tty.setraw(slave)
    ctx = multiprocessing.get_context("fork")
    stop_board, sent = ctx.Event(), ctx.Value("q", 0)
    board = ctx.Process(target=board_process, args=(master, stop_board, sent), daemon=True)
    board.start()
    mem: list[tuple[float, float]] = []
    stop = threading.Event()

    def sample_mem():
        t0 = time.monotonic()
        while not stop.wait(1.0):
            mem.append((time.monotonic() - t0, rss_MB()))

    try:
        opened = open_source(f"serial:{os.ttyname(slave)}", model, tare_s=1.0)
        est = open_estimator(kind, model, EstimatorConfig.box(10.0, mode="async"), cache_dir=cache_dir)
        out = f"/tmp/bench_soak_{label}_{os.getpid()}.csv"
        threading.Timer(duration_s, stop.set).start()
        threading.Thread(target=sample_mem, daemon=True).start()
        with est:
            s = estimate_stream(opened.source, est, out, live=True, stop=stop)
        st = opened.source.stats()
    finally:
        stop.set()
        stop_board.set()
        board.join(5)
        os.close(master)
        os.close(slave)
    os.unlink(out)
    return {"summary": s, "sent": sent.value, "decoder": st.decoder, "mem": mem,
            "tare_window": len(opened.window)}


def memory_growth(mem: list[tuple[float, float]], warm_up_s: float = 60.0) -> dict | None:
    """Resident memory after the warm-up (the first ``warm_up_s``, at most a third of the run) and
    its growth in MB/h and in %/h of the memory after the warm-up.

    The growth is that of the baseline: the least VmRSS of each window of ``max(30 s, run / 20)``,
    Theil-Sen slope through them. The estimators allocate and free large transients (a refresh's
    factorization: VmRSS jumps by ~15 MB for a few seconds, at random times), so a straight line
    through every sample swings by tens of MB/h either way over minutes; what stays held shows in
    the baseline. None with fewer than 4 windows after the warm-up."""
    from scipy.stats import theilslopes

    m = np.array(mem)
    if len(m) < 8:
        return None
    m = m[m[:, 0] >= min(warm_up_s, m[-1, 0] / 3)]
    width = max(30.0, (m[-1, 0] - m[0, 0]) / 20)
    k = ((m[:, 0] - m[0, 0]) // width).astype(int)
    windows = [(m[k == i, 0].mean(), m[k == i, 1].min()) for i in np.unique(k) if (k == i).sum() >= 3]
    if len(windows) < 4:
        return None
    w = np.array(windows)
    slope = theilslopes(w[:, 1], w[:, 0])[0] * 3600.0
    base = float(w[0, 1])
    return {"first_MB": float(mem[0][1]), "base_MB": base, "end_MB": float(w[-1, 1]), "end_s": float(m[-1, 0]),
            "span_s": float(m[-1, 0] - m[0, 0]), "window_s": float(width), "MB_per_h": float(slope),
            "pct_per_h": float(100.0 * slope / base),
            "lsq_MB_per_h": float(np.polyfit(m[:, 0], m[:, 1], 1)[0] * 3600.0)}


def main() -> None:
    logging.getLogger("softphantom").addHandler(message_handler())  # the library's messages, not its progress
    logging.getLogger("softphantom").setLevel(logging.INFO)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=300.0, help="soak of each estimator (s)")
    ap.add_argument("--peer-s", type=float, default=0.0,
                    help="also the latest-sample slot (MAX_LAG_S = 0) for this long, per estimator (0: not)")
    ap.add_argument("--model", default=None, help="model directory (default: the design at --mesh-size-mm)")
    ap.add_argument("--mesh-size-mm", type=float, default=12.0)
    ap.add_argument("--load", type=int, default=2, help="busy processes alongside (0: none)")
    ap.add_argument("--estimator", choices=("atlas", "refresh"), action="append",
                    help="atlas (the default of `softphantom estimate`) and/or refresh (async); repeat for "
                         "both (default: both)")
    ap.add_argument("--cache-dir", default=None, help="where the atlas is cached (default: a temporary directory)")
    add_results_option(ap, "soak")
    a = ap.parse_args()
    kinds = a.estimator or ["atlas", "refresh"]
    model = load_model(a.model) if a.model else build_model(BIPDesign(), a.mesh_size_mm)
    loads = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(a.load)]
    runs = []
    try:
        cache = a.cache_dir or tempfile.mkdtemp(prefix="bench_soak_")
        for kind in kinds:
            r = soak(model, a.duration_s, "queue", kind, cache)
            peer = None
            if a.peer_s > 0:
                lag = stream_mod.MAX_LAG_S
                stream_mod.MAX_LAG_S = 0.0
                try:
                    peer = soak(model, a.peer_s, "latest", kind, cache)
                finally:
                    stream_mod.MAX_LAG_S = lag
            runs.append((kind, r, peer))
    finally:
        for p in loads:
            p.kill()
            p.wait()
    print(f"model: {len(model.nodes)} nodes; board N = {OSR} ({frame_rate_Hz(OSR):.1f} Hz); "
          f"{a.load} busy processes alongside; load average now {os.getloadavg()[0]:.1f}")
    doc = []
    for kind, r, peer in runs:
        for name, res, dur in (("queue", r, a.duration_s), ("latest-slot", peer, a.peer_s)):
            if res is None:
                continue
            s, d = res["summary"], res["decoder"]
            n_in = s["estimates"] + s["skipped"]
            rest = d.frames_ok - n_in - res["tare_window"]
            print(f"{kind}, {name}: {dur:.0f} s, frames sent {res['sent']}, received {d.frames_ok} (= tare window "
                  f"{res['tare_window']} + estimated {s['estimates']} + skipped {s['skipped']} + {rest} read after "
                  f"the stop), skipped {s['skipped'] / max(n_in, 1):.2%} (all counted: lagging > "
                  f"{stream_mod.MAX_LAG_S if name == 'queue' else 0:g} s); decoder lost {d.frames_lost}, "
                  f"duplicates {d.duplicates}, CRC {d.crc_errors}; events {s['events'] or 'none'}; step p50 "
                  f"{s['step_ms_p50']:.2f} ms, p99 {s['step_ms_p99']:.2f} ms, max {s['step_ms_max']:.1f} ms")
        g = memory_growth(r["mem"])
        if g is not None:
            print(f"{kind}: memory (VmRSS) {g['first_MB']:.1f} MB at 1 s; baseline (least of each "
                  f"{g['window_s']:.0f} s) {g['base_MB']:.1f} MB after warm-up, {g['end_MB']:.1f} MB at "
                  f"{g['end_s']:.0f} s; growth {g['MB_per_h']:+.2f} MB/h = {g['pct_per_h']:+.2f} %/h (Theil-Sen "
                  f"over {g['span_s']:.0f} s; a least-squares line through every sample: "
                  f"{g['lsq_MB_per_h']:+.1f} MB/h)")
        s, d = r["summary"], r["decoder"]
        n_in = s["estimates"] + s["skipped"]
        mem = ("n/a (run too short)" if g is None else
               f"{g['base_MB']:.1f} → {g['end_MB']:.1f} MB")
        doc.append((kind, f"{grouped(r['sent'])} / {grouped(d.frames_ok)}", grouped(s["estimates"]),
                    f"{grouped(s['skipped'])} ({s['skipped'] / max(n_in, 1):.1%})", d.frames_lost,
                    f"{s['step_ms_p50']:.1f} / {s['step_ms_p99']:.0f} / {grouped(s['step_ms_max'])} ms", mem,
                    "n/a" if g is None else f"{g['MB_per_h']:+.2f}", "n/a" if g is None else f"{g['pct_per_h']:+.2f}"))
    write_table(a.results_name, ("estimator", "frames sent / received", "estimated", "skipped (counted: lagging)",
                                 "decoder lost", "step p50 / p99 / max", "VmRSS after warm-up → end",
                                 "growth MB/h", "growth %/h"), doc,
                caption=f"{a.duration_s:g} s per estimator, {grouped(len(model.nodes))}-node model, a "
                        f"{frame_rate_Hz(OSR):.0f} Hz board (N = {OSR}) on a pty, {a.load} busy processes beside; "
                        "memory: VmRSS every 1 s; growth: Theil-Sen slope of its baseline (the least of each "
                        "window) after a 60 s warm-up:")


if __name__ == "__main__":
    main()
