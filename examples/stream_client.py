#!/usr/bin/env python3
"""Minimal client of the softphantom estimate stream (ZeroMQ SUB + JSON); needs only pyzmq.

    softphantom live --source synthetic          # in one terminal
    python examples/stream_client.py             # in another (Ctrl-C stops)
    python examples/stream_client.py --endpoint tcp://127.0.0.1:5556 --count 200

Every message is one estimate; keys carry their units (force_y_N, y_mm, pitch_deg, ...), see
docs/stream.md. A gap in ``seq`` means this client read too slowly and the publisher dropped
messages for it (the publisher never waits for a subscriber).
"""

from __future__ import annotations

import argparse
import json
import time

import zmq


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--endpoint", default="tcp://127.0.0.1:5556", help="publisher address")
    ap.add_argument("--count", type=int, default=0, help="stop after this many messages (0: never)")
    ap.add_argument("--timeout-s", type=float, default=10.0, help="give up after this long without a message")
    args = ap.parse_args()

    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.connect(args.endpoint)
    sub.setsockopt(zmq.SUBSCRIBE, b"estimate")  # topic = first frame

    received = lost = 0
    last_seq = None
    try:
        while args.count == 0 or received < args.count:
            if not sub.poll(int(args.timeout_s * 1000)):
                print(f"no message for {args.timeout_s} s from {args.endpoint}")
                break
            _topic, data = sub.recv_multipart()
            m = json.loads(data)
            if last_seq is not None and m["seq"] > last_seq + 1:
                lost += m["seq"] - last_seq - 1
            last_seq = m["seq"]
            received += 1
            latency_ms = (time.time() - m["t_pub_unix_s"]) * 1e3
            print(f"#{m['seq']:6d} t={m['t_s']:8.3f} s  F=({m['force_x_N']:+.2f}, {m['force_y_N']:+.2f}, "
                  f"{m['force_z_N']:+.2f}) N  y={m['y_mm']:+.2f} mm  pitch={m['pitch_deg']:+.2f} deg  "
                  f"transit {latency_ms:.2f} ms", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        sub.close()
        ctx.term()
    print(f"received {received}, lost {lost}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
