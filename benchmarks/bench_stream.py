#!/usr/bin/env python3
"""Stream and live-page benchmark (loopback, this machine).

1. publish rate: messages/s that ``EstimatePublisher.publish`` sustains (encode + send) for real
   estimate messages, and the publish call's p50/p99/max time;
2. latency publish → local subscriber at 77 Hz (the board's fastest) and 1 kHz, p50/p99;
3. page update rate: SSE frames/s a client receives from ``softphantom live`` at 77 Hz estimates;
4. publish call time with a stalled subscriber (never reads, full queue) beside a reading one, and
   the peer: the same burst with the reading subscriber only (tests/test_stream.py counts, this times).

    .venv/bin/python benchmarks/bench_stream.py
"""

from __future__ import annotations

import json
import threading
import time
import urllib.request

import numpy as np

from _results import grouped, write_table
from softphantom.stream import EstimatePublisher, EstimateSubscriber, estimate_to_message
from softphantom.stream.schema import encode
from softphantom.viz.live import LiveConfig, LiveSession, SyntheticSource


def _messages(n: int) -> list[dict]:
    src = SyntheticSource(rate_Hz=1000, duration_s=n / 1000, realtime=False, subdivisions=1)
    return [estimate_to_message(e, i, 0.0) for i, e in enumerate(src)]


def bench_publish(n: int = 20000) -> tuple[str, str]:
    msgs = _messages(n)
    with EstimatePublisher(port=0) as pub, EstimateSubscriber(pub.endpoint, hwm_messages=100000) as sub:
        pub.wait_for_subscribers(1, 5.0)
        got = [0]

        def drain() -> None:
            while sub.recv(timeout_s=1.0) is not None:
                got[0] += 1

        th = threading.Thread(target=drain, daemon=True)
        th.start()
        times = np.empty(n)
        t0 = time.perf_counter()
        for i, m in enumerate(msgs):
            a = time.perf_counter()
            pub.publish(m)
            times[i] = time.perf_counter() - a
        dt = time.perf_counter() - t0
        th.join(5.0)
    size = len(encode(msgs[0]))
    print(f"publish (encode+send, {size} B JSON): {n / dt:,.0f} msg/s; call p50 {np.median(times) * 1e6:.1f} us, "
          f"p99 {np.percentile(times, 99) * 1e6:.1f} us, max {times.max() * 1e3:.2f} ms; "
          f"subscriber got {got[0]}/{n} (unpaced burst)")
    return (f"publish (encode + send, {size} B JSON)",
            f"{grouped(round(n / dt, -2))} msg/s; call p50 {np.median(times) * 1e6:.0f} µs, "
            f"p99 {np.percentile(times, 99) * 1e3:.2f} ms")


def bench_latency(rate_Hz: float, seconds: float = 3.0) -> tuple[str, str]:
    n = int(rate_Hz * seconds)
    msgs = _messages(n)
    lat: list[float] = []
    with EstimatePublisher(port=0) as pub, EstimateSubscriber(pub.endpoint) as sub:
        pub.wait_for_subscribers(1, 5.0)

        def reader() -> None:
            while len(lat) < n:
                m = sub.recv(timeout_s=2.0)
                if m is None:
                    return
                lat.append(time.perf_counter() - m["t_perf"])

        th = threading.Thread(target=reader, daemon=True)
        th.start()
        t0 = time.perf_counter()
        for i, m in enumerate(msgs):
            m["t_perf"] = time.perf_counter()  # same machine: a monotonic clock both sides can read
            pub.publish(m)
            wait = t0 + (i + 1) / rate_Hz - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        th.join(5.0)
        lost = sub.lost
    a = np.array(lat) * 1e3
    print(f"latency publish->subscriber at {rate_Hz:g} Hz: p50 {np.median(a):.3f} ms, p99 {np.percentile(a, 99):.3f} ms, "
          f"max {a.max():.3f} ms; received {len(a)}/{n}, lost {lost}")
    return (f"latency publisher → local subscriber at {rate_Hz:g} Hz",
            f"p50 {np.median(a):.2f} ms, p99 {np.percentile(a, 99):.2f} ms, {len(a)}/{n} received")


def bench_page(seconds: float = 5.0) -> tuple[str, str]:
    src = SyntheticSource(rate_Hz=77, duration_s=None)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=0, view_rate_Hz=30)) as s:
        frames = samples = surfaces = 0
        t_end = time.monotonic() + seconds
        t0 = None
        with urllib.request.urlopen(s.url + "api/events", timeout=10) as r:
            for line in r:
                if not line.startswith(b"data: "):
                    continue
                f = json.loads(line[6:])
                if t0 is None:
                    t0 = time.monotonic()
                    continue  # the first frame carries the history
                frames += 1
                samples += len(f["samples"])
                surfaces += "surface_mm_f32_b64" in f
                if time.monotonic() >= t_end:
                    break
        dt = time.monotonic() - t0
        st = s.state.status()
    print(f"page (SSE, view rate 30 Hz, estimates 77 Hz): {frames / dt:.1f} frames/s, {surfaces / dt:.1f} surface "
          f"updates/s, {samples / dt:.1f} samples/s delivered; estimator rate {st['rate_Hz']} Hz, "
          f"view dropped {st['view_dropped']}")
    return ("page update (`live`, 77 Hz estimates, 30 Hz view)",
            f"{frames / dt:.1f} frames/s; {surfaces / dt:.1f} surface updates/s; {samples / dt:.1f} estimates/s delivered")


def bench_stalled(n: int = 20000) -> tuple[str, str]:
    payload = {"seq": 0, "pad": "x" * 1000}

    def burst(stalled: bool) -> np.ndarray:
        with EstimatePublisher(port=0, hwm_messages=100) as pub, EstimateSubscriber(pub.endpoint) as live:
            extra = EstimateSubscriber(pub.endpoint, hwm_messages=10) if stalled else None
            try:
                pub.wait_for_subscribers(2 if stalled else 1, 5.0)
                times = np.empty(n)
                for i in range(n):
                    payload["seq"] = i
                    a = time.perf_counter()
                    pub.publish(payload)
                    times[i] = time.perf_counter() - a
                    while live.recv(timeout_s=0) is not None:
                        pass
            finally:
                if extra is not None:
                    extra.close()
        return times * 1e3

    peer, st = burst(False), burst(True)
    print(f"publish with a stalled subscriber ({n} x 1 kB): p50 {np.median(st):.4f} ms, p99 "
          f"{np.percentile(st, 99):.4f} ms, max {st.max():.2f} ms; second half p50 {np.median(st[n // 2:]):.4f} ms; "
          f"peer (reading subscriber only) p50 {np.median(peer):.4f} ms, p99 {np.percentile(peer, 99):.4f} ms; "
          f"ratio p50 {np.median(st) / np.median(peer):.2f}")
    return ("publish with a stalled subscriber (queue full)",
            f"call p50 {np.median(st) * 1e3:.1f} µs, p99 {np.percentile(st, 99) * 1e3:.0f} µs (a reading subscriber only: "
            f"{np.median(peer) * 1e3:.1f} / {np.percentile(peer, 99) * 1e3:.0f} µs)")


if __name__ == "__main__":
    rows = [bench_publish(), bench_latency(77.0), bench_latency(1000.0), bench_page(), bench_stalled()]
    write_table("stream", ("measure", "result"), rows)
