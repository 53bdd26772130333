#!/usr/bin/env python3
"""Live page benchmark: frames per second in headless Chromium browsers and the
estimator's step p99 with and without them, all in one live session.

    .venv/bin/python benchmarks/bench_live.py [--model DIR] [--atlas-cache DIR] [--seconds 20] [--browsers 3]

The session is what ``softphantom live --source ... --model DIR`` runs: the atlas estimator (the
default of ``live``) on the default model (~6 k nodes; built once unless ``--model``), in
:class:`~softphantom.viz.live.EstimatorSource`, paced at 77 Hz by the samples' clock. The samples
are a slow push (0 → 3 N along y and back, 4 s period, a little sideways) whose cavity volumes the
atlas itself predicts, so every estimate is a real inversion inside the envelope. The atlas is
built once into ``--atlas-cache`` (grid ``--atlas-grid``, default 3,5,3,2 = 90 solves; its step
costs what a larger grid's does within tens of microseconds: docs/performance/estimation.md).

Phases of ``--seconds`` each, the estimator's step time (``Estimate.step_time``) collected
throughout: no browser; ``--browsers`` clients that only read the event stream (curl: the
server's own cost); one Chromium browser; ``--browsers`` of them (separate processes, 1280×800, the page as a user
opens it: it draws every frame the server sends, at the 30 Hz view rate); the same browsers
orbiting continuously (``?spin=1``: every animation frame is drawn, the page's frame rate); the
last at full resolution (``?scale=1``: no resolution adaptation); the browsers again at
``nice -n 10`` (how a browser on the estimator's machine can be kept out of its way). Then all
again with ``--load`` busy processes (both cores busy); ``--phases`` picks some (``many`` alone:
the three browsers). Per phase: the step p50/p99/max, per browser the frames drawn per second and
the server frames received per second (min / mean), and the CPU the browsers used (every process
of each: renderer, GPU, browser) in cores and per drawn frame — the figure that does not depend on
what else the machine runs.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from _results import markdown_table, write_table  # noqa: E402
from softphantom.progress import message_handler  # noqa: E402
from softphantom.design import BIPDesign, build_model, load_model, save_model  # noqa: E402
from softphantom.estimation import EstimatorConfig, open_estimator  # noqa: E402
from softphantom.estimation.select import atlas_config_from_options  # noqa: E402
from softphantom.sensing import Measurement  # noqa: E402
from softphantom.sensing.sources import SensorSource, SourceStats  # noqa: E402
from softphantom.sensing.protocol import DecoderStats  # noqa: E402
from softphantom.viz.live import EstimatorSource, LiveConfig, LiveSession  # noqa: E402

RATE_HZ = 77.0
PHASES = ("none", "readers", "one", "many", "orbit", "orbit-full", "nice")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
SSE_READER = """
import sys, urllib.request
with urllib.request.urlopen(sys.argv[1] + "api/events") as r:
    while r.read(1 << 16):
        pass
"""


def sse_reader(url: str) -> subprocess.Popen:
    """A client of the event stream that only reads (curl if there is one: little CPU of its own)."""
    curl = shutil.which("curl")
    cmd = [curl, "-sN", url + "api/events", "-o", os.devnull] if curl else [sys.executable, "-c", SSE_READER, url]
    return subprocess.Popen(cmd)


class PushBoard(SensorSource):
    """77 Hz samples of a slow push whose volumes the atlas predicts (no noise), forever."""

    def __init__(self, atlas):
        self.atlas, self.k = atlas, 0
        rest = atlas.volumes(atlas.coords(np.zeros(3), 0.0))[0]
        self._dV = lambda f: atlas.volumes(atlas.coords(f, 0.0))[0] - rest

    def read(self, timeout_s: float = 0.1) -> list[Measurement]:
        out = []
        for _ in range(64):  # a batch; EstimatorSource paces them by t
            t = self.k / RATE_HZ
            s = 0.5 * (1 - math.cos(2 * math.pi * t / 4.0))
            f = np.array([0.3 * math.sin(2 * math.pi * t / 9.0), 3.0 * s, 0.2 * math.cos(2 * math.pi * t / 7.0)])
            out.append(Measurement(t, self.k, t, np.full(5, 51150), 100, np.zeros(4), self._dV(f), 0.0))
            self.k += 1
        return out

    def stats(self) -> SourceStats:
        return SourceStats("ok", DecoderStats())


class Timed:
    """The source with every estimate's step time and wall time kept for the phases."""

    def __init__(self, source):
        self._source, self.geometry = source, source.geometry
        self.steps: list[tuple[float, float]] = []

    def __iter__(self):
        for est in self._source:
            self.steps.append((time.monotonic(), est.step_time * 1e3))
            yield est

    def __getattr__(self, name):
        return getattr(self._source, name)


def model_and_estimator(a):
    model_dir = a.model
    if model_dir is None:
        model_dir = os.path.join(tempfile.gettempdir(), "softphantom_bench_live_model")
        if not os.path.isfile(os.path.join(model_dir, "model.npz")):
            print("meshing the default design ...", flush=True)
            save_model(build_model(BIPDesign()), model_dir)
    model = load_model(model_dir)
    cache = a.atlas_cache or os.path.join(tempfile.gettempdir(), "softphantom_bench_live_atlas")
    os.makedirs(cache, exist_ok=True)
    t0 = time.monotonic()
    est = open_estimator("atlas", model, EstimatorConfig.box(10.0, contact="on-centre", mode="async"),
                         atlas=atlas_config_from_options(a.atlas_grid), cache_dir=cache)
    print(f"model: {len(model.nodes)} nodes, {len(model.outer_faces)} outer triangles; atlas ready in "
          f"{time.monotonic() - t0:.0f} s (cache {cache})", flush=True)
    return model, est


def processes() -> dict[int, tuple[int, str, float]]:
    """pid -> (parent pid, command line, CPU seconds so far (user + system)) of every process."""
    out = {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as fh:
                stat = fh.read()
            with open(f"/proc/{pid}/cmdline") as fh:
                cmd = fh.read().replace("\0", " ")
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()
        out[int(pid)] = (int(fields[1]), cmd, (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"))
    return out


def tree_cpu_s(roots: list[int]) -> list[float]:
    """CPU seconds used so far by each root process and its descendants (a browser: its renderer,
    GPU and utility processes)."""
    ps, kids = processes(), {}
    for pid, (ppid, _, _) in ps.items():
        kids.setdefault(ppid, []).append(pid)
    totals = []
    for root in roots:
        total, stack = 0.0, [root]
        while stack:
            pid = stack.pop()
            if pid in ps:
                total += ps[pid][2]
                stack += kids.get(pid, [])
        totals.append(total)
    return totals


def page_counters(page) -> tuple[int, int, float, float]:
    """(3-D frames drawn, server frames received, the page's clock in ms, its 3-D resolution scale)."""
    return tuple(page.evaluate("() => { const S = window.__softphantomLive; "
                               "return [S.renders, S.frames, performance.now(), S.scale]; }"))


def run_phase(name, seconds, src, pages=(), roots=(), settle_s=3.0):
    # browsers: long enough for a software-rendering page to lower its 3-D scale (x0.8 a second)
    time.sleep(settle_s + (5.0 if pages else 0.0))
    t0, cpu0 = time.monotonic(), tree_cpu_s(roots)
    before = [page_counters(p) for p in pages]
    time.sleep(seconds)
    after = [page_counters(p) for p in pages]
    t1, cpu1 = time.monotonic(), tree_cpu_s(roots)
    steps = np.array([ms for t, ms in src.steps if t0 <= t <= t1])
    row = {"phase": name, "n": len(steps), "p50": np.percentile(steps, 50), "p99": np.percentile(steps, 99),
           "max": steps.max(), "rate": len(steps) / (t1 - t0)}
    if pages:
        dt = [(b[2] - a[2]) / 1e3 for a, b in zip(before, after)]
        fps = [(b[0] - a[0]) / d for a, b, d in zip(before, after, dt)]
        upd = [(b[1] - a[1]) / d for a, b, d in zip(before, after, dt)]
        drawn = sum(b[0] - a[0] for a, b in zip(before, after))
        row.update(fps_min=min(fps), fps_mean=float(np.mean(fps)), upd_min=min(upd), upd_mean=float(np.mean(upd)),
                   scale=float(np.mean([b[3] for b in after])), cores=(sum(cpu1) - sum(cpu0)) / (t1 - t0),
                   ms_frame=1e3 * (sum(cpu1) - sum(cpu0)) / max(drawn, 1))
    line = (f"{name:<44} estimates {row['rate']:5.1f}/s  step p50 {row['p50']:.3f} ms  p99 {row['p99']:.3f} ms  "
            f"max {row['max']:.2f} ms")
    if pages:
        line += (f"  | drawn fps min {row['fps_min']:.1f} mean {row['fps_mean']:.1f}; server frames/s min "
                 f"{row['upd_min']:.1f} mean {row['upd_mean']:.1f}; 3-D scale {row['scale']:.2f}; "
                 f"browsers' CPU {row['cores']:.2f} cores, {row['ms_frame']:.1f} ms per drawn frame")
    print(line, flush=True)
    return row


def main() -> None:
    logging.getLogger("softphantom").addHandler(message_handler())  # the library's messages, not its progress
    logging.getLogger("softphantom").setLevel(logging.INFO)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=None, help="model directory (default: the default design, meshed once)")
    ap.add_argument("--atlas-cache", default=None, help="where the atlas is built once (default: a temp directory)")
    ap.add_argument("--atlas-grid", default="3,5,3,2", help="points per axis of the atlas (NX,NY,NZ,NP)")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each phase")
    ap.add_argument("--browsers", type=int, default=3)
    ap.add_argument("--load", type=int, default=2, help="busy processes in the loaded phases (0: skip them)")
    ap.add_argument("--phases", default=",".join(PHASES),
                    help=f"which phases to run, comma-separated (default all: {','.join(PHASES)})")
    a = ap.parse_args()
    wanted = set(a.phases.split(","))
    if not wanted <= set(PHASES):
        ap.error(f"--phases: unknown {', '.join(sorted(wanted - set(PHASES)))}; known: {', '.join(PHASES)}")
    from playwright.sync_api import sync_playwright

    model, est = model_and_estimator(a)
    src = Timed(EstimatorSource(model, PushBoard(est.atlas), est, live=False, speed=1.0))
    rows, loads = [], []
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None, view_rate_Hz=30.0)) as s, \
            sync_playwright() as pw:
        print(f"live page {s.url}; {a.browsers} browsers; phases of {a.seconds:g} s; "
              f"load average {os.getloadavg()[0]:.1f} at the start", flush=True)
        browsers = []

        niced = os.path.join(tempfile.mkdtemp(prefix="bench_live_"), "chromium-nice")
        with open(niced, "w") as fh:
            fh.write('#!/bin/sh\nexec nice -n 10 /usr/bin/chromium "$@"\n')
        os.chmod(niced, 0o755)

        def open_pages(query: str, exe: str = "/usr/bin/chromium", n: int = a.browsers):
            """n browsers on the page: (pages, the pid of each browser's main process)."""
            for b in browsers:
                b.close()
            browsers.clear()
            pages, roots = [], []
            for _ in range(n):
                known = set(processes())
                b = pw.chromium.launch(executable_path=exe, headless=True, args=CHROMIUM_ARGS)
                new = {pid: v for pid, v in processes().items() if pid not in known
                       and "--user-data-dir=" in v[1] and "--type=" not in v[1]}
                roots += [pid for pid, v in new.items() if v[0] not in new]
                browsers.append(b)
                p = b.new_page(viewport={"width": 1280, "height": 800})
                p.goto(s.url + query)
                p.wait_for_function("() => window.__softphantomLive && window.__softphantomLive.frames > 3",
                                    timeout=60e3)
                pages.append(p)
            return pages, roots

        def phases(tag: str):
            if "none" in wanted:
                rows.append(run_phase(f"no browser{tag}", a.seconds, src))
            if "readers" in wanted:
                readers = [sse_reader(s.url) for _ in range(a.browsers)]
                try:
                    rows.append(run_phase(f"{a.browsers} event-stream readers (no drawing){tag}", a.seconds, src))
                finally:
                    for r in readers:
                        r.kill()
                        r.wait()
            for key, name, query, exe, n in [
                    ("one", "1 browser", "", "/usr/bin/chromium", 1),
                    ("many", f"{a.browsers} browsers", "", "/usr/bin/chromium", a.browsers),
                    ("orbit", f"{a.browsers} browsers orbiting", "?spin=1", "/usr/bin/chromium", a.browsers),
                    ("orbit-full", f"{a.browsers} browsers orbiting, full resolution", "?spin=1&scale=1",
                     "/usr/bin/chromium", a.browsers),
                    ("nice", f"{a.browsers} browsers at nice 10", "", niced, a.browsers)]:
                if key in wanted:
                    rows.append(run_phase(name + tag, a.seconds, src, *open_pages(query, exe, n)))
            for b in browsers:
                b.close()
            browsers.clear()

        phases("")
        if a.load > 0:
            loads = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(a.load)]
            try:
                phases(f", {a.load} busy processes")
            finally:
                for p in loads:
                    p.kill()
                    p.wait()
        st = s.state.status()
    print(f"session: {st['estimates']} estimates, {st['skipped_total']} skipped, view dropped {st['view_dropped']}; "
          f"load average {os.getloadavg()[0]:.1f} at the end")
    cells = []
    for r in rows:
        drawn = f"{r['fps_min']:.1f} / {r['fps_mean']:.1f}" if "fps_min" in r else "—"
        upd = f"{r['upd_min']:.1f} / {r['upd_mean']:.1f}" if "upd_min" in r else "—"
        cells.append([c.replace("nan", "—") for c in (
            r["phase"], f"{r['p50']:.3f} / {r['p99']:.3f} / {r['max']:.2f}", drawn, upd, f"{r.get('scale', math.nan):.2f}",
            f"{r.get('cores', math.nan):.2f}", f"{r.get('ms_frame', math.nan):.1f}")])
    header = ("phase", "step p50 / p99 / max ms", "drawn frames/s (min / mean over browsers)", "server frames/s",
              "3-D scale", "browsers' CPU (cores)", "CPU ms per drawn frame")
    print("\n" + markdown_table(header, cells))
    write_table("live", header, cells, caption=f"{a.browsers} headless Chromium browsers (WebGL in software), "
                                               f"phases of {a.seconds:g} s, 77 Hz estimates:")


if __name__ == "__main__":
    main()
