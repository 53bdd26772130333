"""Helpers for tests that start a real ``softphantom`` process."""

from __future__ import annotations

import signal


def sigint_default() -> None:
    """``preexec_fn`` for a child that a test will interrupt: SIGINT back to its default. A job a
    non-interactive shell starts in the background (``make test &``) ignores SIGINT, its children
    inherit that, and Python then never installs its KeyboardInterrupt handler: the Ctrl-C tests
    sent a signal nobody heard (they failed in every backgrounded suite, passed in the foreground)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
