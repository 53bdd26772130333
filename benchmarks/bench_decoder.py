"""Decoder throughput against the board's fastest frame rates, and the long fuzz of the decoder.

    .venv/bin/python benchmarks/bench_decoder.py [--fuzz-frames 1000000] [--fault-rate 0.02]

Prints frames/s for (a) the stream decoder alone (COBS + CRC + unpack + counters) and (b) the whole
host path to a Measurement (decode + tare + Boyle), and the head-room over the board's rates:
the 77 Hz mode (N = 25), the UART-bound maximum at 115200 baud (35-byte frames), and the
ADC-bound maximum (N = 1). Then the fuzz: ``--fuzz-frames`` DATA frames per protocol version
with line faults of every kind (softphantom.sensing.faults: bit flips, truncations, lost
delimiters, noise bursts over a frame and between frames) at ``--fault-rate``, fed in random
chunks: crashes, frames accepted that the board never sent, frames lost per damaging fault (1.00
is the goal: a damaged frame costs only itself) and per harmless fault (0), and the decoder's
own ``frames_lost`` counter against the truth. Seeded.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from _results import grouped, write_table
from softphantom.sensing.board import frame_rate_Hz, uart_bytes_per_s
from softphantom.sensing.chain import default_chain
from softphantom.sensing.faults import DAMAGING, FAULT_KINDS, faulty_stream
from softphantom.sensing.protocol import DATA_FRAME_BYTES, DataFrame, StreamDecoder, encode_data
from softphantom.sensing.sources import FrameSource


def fuzz(n_frames: int, fault_rate: float, version: int, seed: int = 0, block: int = 50_000) -> dict:
    """Run ``n_frames`` faulty frames through one decoder (blocks of consecutive seqs)."""
    rng = np.random.default_rng([seed, version])
    dec = StreamDecoder()
    crashes = invented = lost = got_total = 0
    per_kind = {k: [0, 0] for k in FAULT_KINDS}          # kind -> [faults, frames lost]
    t0 = time.perf_counter()
    for start in range(0, n_frames, block):
        n = min(block, n_frames - start)
        sf = faulty_stream(n, fault_rate, rng, version=version, start_seq=start)
        # a fresh seq range per block: the first frame of a block follows the last of the previous
        sent = set(sf.seqs.tolist())
        got = []
        pos = 0
        while pos < len(sf.data):
            c = int(rng.integers(1, 512))
            try:
                got += [f.seq for f in dec.feed(sf.data[pos:pos + c]) if isinstance(f, DataFrame)]
            except Exception:                              # noqa: BLE001 - counting is the point
                crashes += 1
            pos += c
        invented += sum(1 for s in got if s not in sent)
        missing = sent - set(got)
        lost += len(missing)
        got_total += len(got)
        for k, kind in sf.faults:
            per_kind[kind][0] += 1
            per_kind[kind][1] += int(sf.seqs[k]) in missing
    wall = time.perf_counter() - t0
    st = dec.stats
    damaging = sum(v[0] for k, v in per_kind.items() if k in DAMAGING)
    harmless = sum(v[0] for k, v in per_kind.items() if k not in DAMAGING)
    lost_d = sum(v[1] for k, v in per_kind.items() if k in DAMAGING)
    return {"version": version, "frames": n_frames, "faults": damaging + harmless, "crashes": crashes,
            "invented": invented, "lost": lost, "counter_lost": st.frames_lost,
            "per_damaging": lost_d / max(damaging, 1), "per_harmless": (lost - lost_d) / max(harmless, 1),
            "per_kind": {k: v[1] / max(v[0], 1) for k, v in per_kind.items()}, "wall_s": wall,
            "stats": st}


def main(n: int = 50_000, chunk: int = 4096, fuzz_frames: int = 1_000_000, fault_rate: float = 0.02) -> None:
    rng = np.random.default_rng(0)
    raws = rng.integers(10_000, 25_000, (n, 5))          # within 0..1023·25 (the content check)
    stream = b"".join(encode_data(k & 0xFFFF, 13_000 * k & 0xFFFFFFFF, 25, raws[k]) for k in range(n))
    chunks = [stream[i:i + chunk] for i in range(0, len(stream), chunk)]

    best = 0.0
    for _ in range(3):
        dec = StreamDecoder()
        t0 = time.perf_counter()
        for c in chunks:
            dec.feed(c)
        best = max(best, n / (time.perf_counter() - t0))
        assert dec.stats.frames_ok == n
    full = 0.0
    for _ in range(2):
        src = FrameSource(chunks, default_chain())
        t0 = time.perf_counter()
        k = sum(1 for _ in src)
        full = max(full, k / (time.perf_counter() - t0))
        assert k == n
    rates = {"77 Hz mode (N = 25)": frame_rate_Hz(25),
             "UART-bound max, 115200 baud": uart_bytes_per_s(115_200) / DATA_FRAME_BYTES,
             "ADC-bound max (N = 1)": frame_rate_Hz(1)}
    print(f"stream decoder:          {best:>10,.0f} frames/s ({n} frames, {chunk}-byte chunks)")
    print(f"decode → Measurement:    {full:>10,.0f} frames/s")
    for name, r in rates.items():
        print(f"  vs {name:<30} {r:>7.1f} Hz: decoder {best / r:>7.0f}×, full path {full / r:>6.0f}×")
    r77 = rates["77 Hz mode (N = 25)"]
    write_table("decoder", ("path", "frames/s", "vs the 77 Hz board mode"), [
        ("COBS + CRC decoder alone", grouped(round(best, -2)), f"{grouped(best / r77)}×"),
        ("decoder + conversion to `Measurement`", grouped(full), f"{grouped(full / r77)}×")], right=(1, 2),
        caption=f"{grouped(n)} frames fed in {chunk}-byte chunks, best of 3:")
    if fuzz_frames <= 0:
        return
    fuzz_rows = []
    print(f"\nfuzz: {fuzz_frames:,} frames per version, fault rate {fault_rate:g} (every kind), random chunks")
    for version in (1, 2):
        r = fuzz(fuzz_frames, fault_rate, version)
        s = r["stats"]
        print(f"  version {version}: {r['faults']:,} faults, crashes {r['crashes']}, frames invented "
              f"{r['invented']}, lost {r['lost']:,} (decoder's counter {r['counter_lost']:,}); "
              f"lost per damaging fault {r['per_damaging']:.4f}, per harmless fault {r['per_harmless']:.4f}; "
              f"{r['frames'] / r['wall_s']:,.0f} frames/s")
        fuzz_rows.append((version, grouped(r["frames"]), grouped(r["faults"]), r["crashes"], r["invented"],
                          f"{r['per_damaging']:.4f}", f"{r['per_harmless']:.4f}",
                          "yes" if r["counter_lost"] == r["lost"] else f"no ({r['counter_lost']} vs {r['lost']})",
                          grouped(r["frames"] / r["wall_s"])))
        print("    per kind: " + ", ".join(f"{k} {v:.4f}" for k, v in r["per_kind"].items())
              + f"; crc {s.crc_errors:,}, malformed {s.malformed:,}, content {s.content_errors}, "
              f"overflows {s.overflows}, recovered {s.recovered:,}")

    write_table("decoder_fuzz", ("protocol", "frames", "faults", "crashes", "frames invented", "lost per damaging fault",
                                 "lost per harmless fault", "decoder's count = truth", "frames/s"), fuzz_rows,
                right=(1, 2, 3, 4, 5, 6, 8),
                caption=f"Every fault kind of `softphantom.sensing.faults` at a rate of {fault_rate:g}, "
                        "random chunks of 1–511 bytes, seeded:")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=50_000, help="frames for the throughput figures")
    ap.add_argument("--fuzz-frames", type=int, default=1_000_000, help="frames per version for the fuzz (0: none)")
    ap.add_argument("--fault-rate", type=float, default=0.02, help="fraction of frames given a fault")
    a = ap.parse_args()
    main(a.frames, fuzz_frames=a.fuzz_frames, fault_rate=a.fault_rate)
