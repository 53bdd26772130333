"""Decoder throughput against the board's fastest frame rates.

    .venv/bin/python benchmarks/bench_decoder.py

Prints frames/s for (a) the stream decoder alone (COBS + CRC + unpack + counters) and (b) the whole
host path to a Measurement (decode + tare + Boyle), and the head-room over the board's rates:
the 77 Hz mode (N = 25), the UART-bound maximum at 115200 baud (34-byte frames), and the
ADC-bound maximum (N = 1).
"""

from __future__ import annotations

import time

import numpy as np

from softphantom.sensing.board import frame_rate_Hz, uart_bytes_per_s
from softphantom.sensing.chain import default_chain
from softphantom.sensing.protocol import DATA_FRAME_BYTES, StreamDecoder, encode_data
from softphantom.sensing.sources import FrameSource


def main(n: int = 50_000, chunk: int = 4096) -> None:
    rng = np.random.default_rng(0)
    raws = rng.integers(40_000, 60_000, (n, 5))
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


if __name__ == "__main__":
    main()
