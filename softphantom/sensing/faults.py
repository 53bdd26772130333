"""Line faults on the board's byte stream, for tests, the fuzz benchmark and the virtual phantom.

Each fault touches one frame (or the gap after it), so "frames lost per fault" is exact: a
decoder that resynchronises at once loses 1 frame per *damaging* fault (a flipped bit in the body,
a truncated frame, a noise burst over the body) and 0 per *harmless* one (a lost delimiter in a
version 2 stream or at the head of a version 1 merge, noise between two frames).

>>> import numpy as np
>>> from softphantom.sensing.protocol import StreamDecoder
>>> sf = faulty_stream(200, 0.1, np.random.default_rng(0))
>>> got = {f.seq for f in StreamDecoder().feed(sf.data) if hasattr(f, "raw")}
>>> sf.n_faults > 0, len(set(range(200)) - got) <= sf.n_damaging
(True, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softphantom.errors import UserError
from softphantom.sensing.protocol import PROTOCOL_VERSION, encode_data

FAULT_KINDS = ("flip", "truncate", "delimiter", "burst", "insert")
"""``flip`` 1–3 bits in the frame's body, ``truncate`` the frame cut short (a board reset),
``delimiter`` its trailing 0x00 lost, ``burst`` line noise over part of its body, ``insert`` line
noise between it and the next frame."""
DAMAGING = {"flip", "truncate", "burst"}


@dataclass(frozen=True)
class FaultyStream:
    """``data`` the bytes, ``seqs`` (n,) the DATA frames sent, ``faults`` (frame index, kind)."""

    data: bytes
    seqs: np.ndarray
    faults: tuple[tuple[int, str], ...]

    @property
    def n_faults(self) -> int:
        return len(self.faults)

    @property
    def n_damaging(self) -> int:
        return sum(1 for _, k in self.faults if k in DAMAGING)


def _body_span(frame: bytes) -> tuple[int, int]:
    """[start, end) of the COBS body inside a frame (without its delimiters)."""
    return (1 if frame[0] == 0 else 0), len(frame) - 1


def damage(frame: bytes, kind: str, rng: np.random.Generator) -> bytes:
    """One frame with fault ``kind`` applied (``insert`` appends the noise after it)."""
    a, b = _body_span(frame)
    f = bytearray(frame)
    if kind == "flip":
        for pos in rng.choice(np.arange(a, b), size=int(rng.integers(1, 4)), replace=False):
            f[pos] ^= 1 << int(rng.integers(0, 8))
        return bytes(f)
    if kind == "truncate":                       # at least one body byte kept, at least one lost
        return bytes(f[: int(rng.integers(a + 1, b))])
    if kind == "delimiter":
        return bytes(f[:-1])
    if kind == "burst":
        p = int(rng.integers(a, b))
        n = int(rng.integers(1, b - p + 1))
        f[p:p + n] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        return bytes(f)
    if kind == "insert":
        return bytes(f) + rng.integers(0, 256, int(rng.integers(1, 80)), dtype=np.uint8).tobytes()
    raise UserError(f"fault kind: expected one of {', '.join(FAULT_KINDS)}, got {kind!r}")


def faulty_stream(n: int, fault_rate: float, rng: np.random.Generator, version: int = PROTOCOL_VERSION,
                  kinds: tuple[str, ...] = FAULT_KINDS, osr: int = 25, start_seq: int = 0) -> FaultyStream:
    """``n`` DATA frames (77 Hz clock at ``osr`` 25) of which a fraction ``fault_rate`` gets a
    fault of a kind drawn from ``kinds``; never two faults in adjacent frames, so each fault is
    counted on its own. Seeded by ``rng``."""
    if not 0.0 <= fault_rate <= 0.5:
        raise UserError(f"fault_rate: must be in [0, 0.5], got {fault_rate}")
    period_us = 5 * osr * 104
    raw = rng.integers(100 * osr, 900 * osr, (n, 5))
    hit = rng.random(n) < fault_rate
    hit[1:] &= ~hit[:-1]                          # no two adjacent frames
    hit[0] = hit[-1] = False                      # a gap needs a frame before and after it
    out = bytearray()
    faults = []
    for k in range(n):
        fr = encode_data((start_seq + k) & 0xFFFF, (k * period_us) & 0xFFFFFFFF, osr, raw[k], version=version)
        if hit[k]:
            kind = kinds[int(rng.integers(0, len(kinds)))]
            fr = damage(fr, kind, rng)
            faults.append((k, kind))
        out += fr
    return FaultyStream(bytes(out), (start_seq + np.arange(n)) & 0xFFFF, tuple(faults))
