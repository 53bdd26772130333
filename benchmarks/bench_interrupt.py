"""Ctrl-C → exit latency of the command line (docs/robustness.md).

SIGINT is sent to a real ``softphantom`` process while it works, and the time until it has exited
is measured (exit code 130 checked, no output left):

- ``design --mesh-size-mm 2`` while gmsh meshes (~250 000 tets), gmsh in its child process;
- ``virtual run`` while the truth is solved (Python/SciPy);
- peer, in the same run: gmsh in-process on the main thread (how ``design`` ran before): Ctrl-C
  waits for the mesh to finish (``--peer-mesh-size-mm``, 3 mm by default).

Each case idle and again with both cores busy (two spinning load processes started here).

    .venv/bin/python benchmarks/bench_interrupt.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _results import write_table

PEER = """
import sys
from softphantom.design import BIPDesign
from softphantom.design.mesh import mesh_design
d = BIPDesign()
print("meshing", flush=True)
mesh_design(d, d.mesh.scaled_to(float(sys.argv[1])), isolate=False)
"""


def _spin() -> None:
    while True:
        pass


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _interrupt(cmd, cwd, ready, settle_s) -> tuple[float, int]:
    # SIGINT back to its default in the child: a backgrounded job ignores it, and so would Python
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        while not ready(proc) and proc.poll() is None:
            time.sleep(0.02)
        time.sleep(settle_s)  # well inside the work: gmsh in generate(3), the truth in its solves
        assert proc.poll() is None, "finished before the interrupt"
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGINT)
        proc.wait(300)
        return time.perf_counter() - t0, proc.returncode
    finally:
        if proc.poll() is None:
            proc.kill()


def _cases(work: Path, peer_h: float):
    py = [sys.executable, "-m", "softphantom"]
    started: dict[str, float] = {}

    def after(s):
        def ready(proc):
            started.setdefault(str(proc.pid), time.monotonic())
            return time.monotonic() - started[str(proc.pid)] > s
        return ready

    return [
        ("design --mesh-size-mm 2 (gmsh child)", py + ["design", "--out", "d", "--no-png", "--mesh-size-mm", "2"],
         lambda p: bool(_children(p.pid)), 4.0),
        ("virtual run (truth solve)", py + ["virtual", "run", "--scenario", "needle-insertion", "--model", "model",
                                            "--out", "run"], after(5.0), 0.0),
        (f"peer: gmsh in-process at {peer_h:g} mm", [sys.executable, "-c", PEER, str(peer_h)],
         lambda p: p.stdout.readline().startswith("meshing"), 4.0),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--peer-mesh-size-mm", type=float, default=3.0)
    a = ap.parse_args()
    from softphantom.design import BIPDesign, build_model, save_model

    cells: dict[str, dict[str, str]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        save_model(build_model(BIPDesign(), 12.0), work / "model")
        for label, n_load in (("idle", 0), ("both cores busy", 2)):
            load = [mp.Process(target=_spin, daemon=True) for _ in range(n_load)]
            for p in load:
                p.start()
            try:
                print(f"== {label}")
                for name, cmd, ready, settle_s in _cases(work, a.peer_mesh_size_mm):
                    lat = []
                    for _ in range(a.repeat):
                        s, code = _interrupt(cmd, work, ready, settle_s)
                        lat.append(s)
                        left = sorted(p.name for p in work.iterdir() if p.name != "model")
                        assert not left, f"{name}: left {left}"
                        if "peer" not in name:
                            assert code == 130, f"{name}: exit {code}"
                    med = sorted(lat)[len(lat) // 2]
                    print(f"  {name:42s} SIGINT → exit: median {med:.2f} s, max {max(lat):.2f} s ({a.repeat} runs)")
                    cells.setdefault(name, {})[label] = f"{med:.2f} / {max(lat):.2f} s"
            finally:
                for p in load:
                    p.kill()
    write_table("interrupt", ("case", "idle: median / max", "both cores busy: median / max"),
                [(name, c.get("idle", "—"), c.get("both cores busy", "—")) for name, c in cells.items()],
                caption=f"SIGINT to a real `softphantom` process in the middle of its work; time until it exited "
                        f"(exit code 130 and nothing left in the output directory, checked every time), {a.repeat} runs:")


if __name__ == "__main__":
    main()
