"""Network stream of every estimate: ZeroMQ PUB/SUB, one JSON message per estimate.

Wire format: a two-frame ZeroMQ message ``[b"estimate", <JSON>]`` (see
:mod:`softphantom.stream.schema` and docs/stream.md). The publisher binds
``tcp://127.0.0.1:<port>`` unless told another host.

Never blocking the estimator: :meth:`EstimatePublisher.publish` hands the bytes to ZeroMQ's I/O
thread with ``NOBLOCK``. ZeroMQ keeps one bounded queue per subscriber (``SNDHWM`` messages); when a
slow or vanished subscriber's queue is full, new messages *for that subscriber only* are dropped and
the others go on. A subscriber counts what it lost from gaps in ``seq``
(:class:`EstimateSubscriber` does).

>>> with EstimatePublisher(port=0) as pub, EstimateSubscriber(pub.endpoint) as sub:
...     ok = pub.wait_for_subscribers(1, timeout_s=5.0)
...     ok = pub.publish({"seq": 0, "force_y_N": 1.5})
...     sub.recv(timeout_s=5.0)["force_y_N"], sub.lost
(1.5, 0)
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any, Mapping

import zmq

from softphantom.errors import UserError
from softphantom.stream.schema import TOPIC_ESTIMATE, encode

DEFAULT_STREAM_PORT = 5556


@dataclass(frozen=True)
class PublisherStats:
    """Counters of a publisher: ``sent`` messages, ``subscribers`` now connected (as ZeroMQ tells),
    ``would_block`` sends refused by ZeroMQ (dropped for everyone; 0 with PUB semantics), and
    ``max_publish_ms`` the longest :meth:`EstimatePublisher.publish` call so far."""

    sent: int
    subscribers: int
    would_block: int
    max_publish_ms: float


class EstimatePublisher:
    """Publish estimate messages on ``tcp://host:port`` (``port=0``: a free port, see ``endpoint``).

    ``host`` defaults to loopback; listening on another interface must be asked for explicitly.
    ``hwm_messages`` bounds each subscriber's queue. Not thread-safe: publish from one thread.
    """

    def __init__(self, port: int = DEFAULT_STREAM_PORT, host: str = "127.0.0.1", hwm_messages: int = 1000,
                 topic: str = TOPIC_ESTIMATE):
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.XPUB)  # XPUB: a PUB that also reports subscriptions
        self._sock.setsockopt(zmq.SNDHWM, int(hwm_messages))
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.XPUB_VERBOSER, 1)  # every (un)subscribe, so we can count peers
        # ZeroMQ's spelling: "*" for every interface ("" to a socket), IPv6 literals in brackets
        where = "*" if host == "" else f"[{host.strip('[]')}]" if ":" in host else host
        if ":" in host:
            self._sock.setsockopt(zmq.IPV6, 1)
        try:
            if port == 0:
                p = self._sock.bind_to_random_port(f"tcp://{where}")
            else:
                self._sock.bind(f"tcp://{where}:{int(port)}")
                p = int(port)
        except zmq.ZMQError as exc:
            self._ctx.destroy(linger=0)
            raise UserError(f"cannot listen for the stream on {where}:{port}: {exc}") from None
        self.host, self.port = ("0.0.0.0" if host == "" else where), p
        self._topic = topic.encode()
        self._sent = 0
        self._subs = 0
        self._would_block = 0
        self._max_pub = 0.0

    @property
    def endpoint(self) -> str:
        """``tcp://host:port`` that subscribers connect to."""
        return f"tcp://{self.host}:{self.port}"

    def _poll_subscriptions(self) -> None:
        while True:
            try:
                ev = self._sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return
            if ev[:1] == b"\x01":
                self._subs += 1
            elif ev[:1] == b"\x00":
                self._subs = max(0, self._subs - 1)

    def publish(self, message: Mapping[str, Any] | bytes) -> bool:
        """Send one message (a dict, JSON-encoded here, or ready bytes); never blocks.

        Returns ``False`` when ZeroMQ refused it outright (counted in ``would_block``).
        """
        t0 = time.perf_counter()
        data = message if isinstance(message, bytes) else encode(message)
        self._poll_subscriptions()
        try:
            self._sock.send_multipart([self._topic, data], flags=zmq.NOBLOCK, copy=len(data) < 65536)
            self._sent += 1
            ok = True
        except zmq.Again:
            self._would_block += 1
            ok = False
        self._max_pub = max(self._max_pub, time.perf_counter() - t0)
        return ok

    def wait_for_subscribers(self, n: int = 1, timeout_s: float = 5.0) -> bool:
        """Wait (at most ``timeout_s``) until ``n`` subscribers have subscribed; ``True`` if they did.

        Useful before a run whose first messages must not be lost (ZeroMQ's "slow joiner").
        """
        end = time.monotonic() + timeout_s
        while self._subs < n:
            left = end - time.monotonic()
            if left <= 0:
                return False
            if self._sock.poll(int(min(left, 0.05) * 1000), zmq.POLLIN):
                self._poll_subscriptions()
        return True

    def stats(self) -> PublisherStats:
        """Current counters (see :class:`PublisherStats`)."""
        return PublisherStats(self._sent, self._subs, self._would_block, self._max_pub * 1e3)

    def close(self) -> None:
        """Close the socket (unsent messages are discarded) and its context."""
        self._ctx.destroy(linger=0)  # closes the socket too; never waits

    def __enter__(self) -> "EstimatePublisher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class EstimateSubscriber:
    """A subscriber to an :class:`EstimatePublisher` that counts lost messages from ``seq`` gaps.

    ``received`` messages so far, ``lost`` messages that never arrived (the publisher dropped them
    for this subscriber because it read too slowly), ``out_of_order`` (never expected).
    """

    def __init__(self, endpoint: str, hwm_messages: int = 1000, topic: str = TOPIC_ESTIMATE):
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.setsockopt(zmq.RCVHWM, int(hwm_messages))
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.connect(endpoint)
        self._sock.setsockopt(zmq.SUBSCRIBE, topic.encode())
        self.received = 0
        self.lost = 0
        self.out_of_order = 0
        self._last_seq: int | None = None

    def recv(self, timeout_s: float = 1.0) -> dict[str, Any] | None:
        """The next message as a dict, or ``None`` after ``timeout_s`` without one."""
        if not self._sock.poll(int(timeout_s * 1000), zmq.POLLIN):
            return None
        _topic, data = self._sock.recv_multipart()
        msg = json.loads(data)
        seq = msg.get("seq")
        if isinstance(seq, int):
            if self._last_seq is not None:
                if seq > self._last_seq + 1:
                    self.lost += seq - self._last_seq - 1
                elif seq <= self._last_seq:
                    self.out_of_order += 1
            self._last_seq = seq
        self.received += 1
        return msg

    def close(self) -> None:
        self._ctx.destroy(linger=0)

    def __enter__(self) -> "EstimateSubscriber":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
