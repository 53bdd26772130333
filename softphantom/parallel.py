"""One Dask set-up for the work that outgrows one process: offline estimator builds, calibration,
design sweeps.

A local cluster (processes, one thread each, all cores) by default; an existing scheduler by its
address (``--scheduler tcp://host:8786``). Tasks are plain functions of picklable arguments; the
result of each task comes back with its error, so one failed item never stops a batch.

>>> from softphantom.parallel import dask_client, map_tasks
>>> with dask_client(processes=False, n_workers=1) as client:
...     out = map_tasks(client, pow, [(2, 3), (3, 2), (0, -1)], label="pow")
>>> [o.value for o in out[:2]], out[2].ok, out[2].error
([8, 9], False, 'ZeroDivisionError: 0.0 cannot be raised to a negative power')
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from softphantom.errors import UserError
from softphantom.progress import report

log = logging.getLogger(__name__)

#: Seconds to wait for an existing scheduler before refusing it.
CONNECT_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class TaskResult:
    """One task's outcome: ``value`` when ``ok``, else ``error`` (one line: type and message)."""

    index: int
    ok: bool
    value: Any = None
    error: str = ""


@contextmanager
def dask_client(
    scheduler: str | None = None,
    n_workers: int | None = None,
    processes: bool = True,
    background: bool = False,
) -> Iterator[Any]:
    """A ``distributed.Client``: on ``scheduler`` (an address) if given, else on a new local cluster.

    The local cluster has ``n_workers`` (default: the machine's cores) single-threaded worker
    processes, so numba/BLAS in each worker do not fight for the same cores; it is closed on exit.
    ``background``: its worker processes run at a lower priority (:data:`BACKGROUND_NICE`), for a
    command that runs something in real time beside them (the demo's estimator beside its truth
    solves). An unreachable scheduler raises :class:`UserError` naming the address.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - a core dependency
        raise UserError("dask[distributed] is not installed: pip install 'dask[distributed]'") from exc
    if scheduler is not None:
        if not scheduler.strip():
            raise UserError("--scheduler: empty address (give tcp://HOST:PORT or leave it out)")
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as exc:
            raise UserError(f"--scheduler {scheduler}: unreachable ({type(exc).__name__}: {exc})") from None
        except ValueError as exc:  # distributed's address parser: no port, unknown scheme
            raise UserError(f"--scheduler {scheduler!r}: not a scheduler address ({exc}); give tcp://HOST:PORT") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = int(n_workers or os.cpu_count() or 1)
    if n < 1:
        raise UserError(f"n_workers must be >= 1, got {n}")
    import dask

    # Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=64 KiB (to hand memory back to the OS):
    # that also fixes glibc's mmap threshold at 128 KiB, so every array above it (a 6 mm model's
    # force vector: 145 KB) is a fresh mmap, zero-filled page by page, unmapped when freed — an atlas
    # build spent 20 % of its CPU in the kernel on those page faults. glibc's own default here.
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=processes,
            dashboard_address=":0",  # a free port: None still binds the default 8787 and warns when taken
            # CRITICAL: a worker logs ERROR with a multi-line traceback when a heartbeat misses the
            # closing scheduler (seen under load at shutdown); task failures reach map_tasks as results
            silence_logs=50,
        )
    client = Client(cluster)
    try:
        if background and processes:
            client.run(os.nice, BACKGROUND_NICE)
        yield client
    finally:
        _stop_workers(cluster)
        client.close()
        cluster.close()


BACKGROUND_NICE = 10
"""How much lower a background cluster's workers run (``os.nice``): the kernel then gives a
real-time loop in the main process the core whenever it is ready."""


def _stop_workers(cluster: Any) -> None:
    """End a local cluster's worker processes at once (SIGTERM). Their results are in, or no longer
    wanted (Ctrl-C): the nanny's own close asks each worker to finish its task first and kills it
    only after 4 s ("Worker process still alive after 4.0 seconds, killing"), which held Ctrl-C
    for seconds while a worker was meshing."""
    import signal

    for nanny in list(getattr(cluster, "workers", {}).values()):
        pid = getattr(nanny, "pid", None)
        if not pid:
            continue
        if hasattr(nanny, "close_gracefully"):
            nanny.close_gracefully(reason="softphantom-done")  # a worker that exits is not restarted
        try:
            os.kill(pid, signal.SIGTERM)
        except (ProcessLookupError, PermissionError):
            pass


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


def map_tasks(
    client: Any,
    fn: Callable[..., Any],
    args: Sequence[tuple],
    label: str | None = "tasks",
    on_result: Callable[[TaskResult], None] | None = None,
) -> list[TaskResult]:
    """Run ``fn(*a)`` for each ``a`` in ``args`` on ``client``; results in input order.

    Reports its progress here, on the client, as each task ends (:func:`softphantom.progress.report`:
    task ``label``, done/total; the CLI draws a bar) unless ``label`` is None; ``on_result`` sees each
    result as it arrives (for caching, resuming). A task that raises gives ``TaskResult(ok=False,
    error=...)``; the others go on.
    """
    from distributed import as_completed

    futures = [client.submit(fn, *a, pure=False) for a in args]
    index = {f.key: i for i, f in enumerate(futures)}
    out: list[TaskResult | None] = [None] * len(futures)

    if label is not None and futures:
        report(log, label, 0, len(futures))
    for done, fut in enumerate(as_completed(futures), 1):
        i = index[fut.key]
        try:
            res = TaskResult(i, True, fut.result())
        except Exception as exc:  # noqa: BLE001 - recorded per task, never fatal to the batch
            res = TaskResult(i, False, error=_describe(exc))
        out[i] = res
        if on_result is not None:
            on_result(res)
        if label is not None:
            report(log, label, done, len(futures))
    return [r for r in out if r is not None]
