"""The shared Dask set-up: local cluster, per-task errors, refusal of an unreachable scheduler."""

import json
import os
import socket
import subprocess
import sys

import pytest

from softphantom.errors import UserError
from softphantom.parallel import dask_client, map_tasks


def _square(x):
    if x == 3:
        raise ValueError("three is refused")
    return x * x


@pytest.fixture(scope="module")
def local_cluster():
    """A local cluster of two worker processes (started once: ~3 s each time)."""
    with dask_client(n_workers=2) as client:
        yield client


def test_local_processes_keep_order_and_record_errors(local_cluster):
    seen = []
    out = map_tasks(local_cluster, _square, [(i,) for i in range(6)], on_result=seen.append)
    assert [r.index for r in out] == list(range(6))
    assert [r.value for r in out if r.ok] == [0, 1, 4, 16, 25]
    assert out[3].ok is False and out[3].error == "ValueError: three is refused"
    assert sorted(r.index for r in seen) == list(range(6))


def test_unreachable_scheduler_is_one_line_user_error(monkeypatch):
    import softphantom.parallel as par

    monkeypatch.setattr(par, "CONNECT_TIMEOUT_S", 0.2)  # nobody listens: refused at once, retried until then
    with socket.socket() as s:  # a free port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(UserError) as err:
        with dask_client(f"tcp://127.0.0.1:{port}"):
            pass
    msg = str(err.value)
    assert f"tcp://127.0.0.1:{port}" in msg and "unreachable" in msg and "\n" not in msg



def test_one_blas_thread_per_process_unless_the_user_says_otherwise():
    # numpy's OpenBLAS sizes its pool when it loads, CHOLMOD's (the system's) too: softphantom must set
    # the default before either; counted by threadpoolctl (an independent reader of the pools)
    code = ("import json, softphantom, numpy, sksparse.cholmod; from threadpoolctl import threadpool_info; "
            "print(json.dumps([(i['internal_api'], i['num_threads']) for i in threadpool_info()]))")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    pools = json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                      check=True).stdout)
    assert [n for api, n in pools if api == "openblas"] == [1, 1]  # numpy's and the system's (CHOLMOD)
    env["OPENBLAS_NUM_THREADS"] = "2"  # the user's setting wins
    pools = json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                      check=True).stdout)
    assert [n for api, n in pools if api == "openblas"] == [2, 2]


def test_pools_loaded_before_softphantom_are_capped_too():
    # a script that imports numpy (and CHOLMOD's BLAS) before softphantom: the environment defaults
    # come too late for those pools; softphantom caps them with threadpoolctl, the user's setting wins
    if (os.cpu_count() or 1) < 2:
        pytest.skip("one core: every pool has one thread anyway")
    code = ("import json, numpy, sksparse.cholmod, softphantom; from threadpoolctl import threadpool_info; "
            "print(json.dumps([(i['internal_api'], i['num_threads']) for i in threadpool_info()]))")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS") and not k.startswith("OMP_")}
    pools = json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                      check=True).stdout)
    assert [n for api, n in pools if api == "openblas"] == [1, 1]
    assert all(n == 1 for api, n in pools if api == "openmp")
    env["OPENBLAS_NUM_THREADS"] = "2"
    pools = json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                      check=True).stdout)
    assert [n for api, n in pools if api == "openblas"] == [2, 2]


def _alloc_faults():
    import resource

    import numpy as np

    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(200):
        a = np.ones(1 << 17)  # 1 MB written, then freed: a force vector's life in a Newton loop
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0


def test_workers_reuse_freed_memory_without_page_faults(local_cluster):
    # Dask's default MALLOC_TRIM_THRESHOLD_ makes every freed 1 MB array go back to the OS and the
    # next one fault in its 256 pages again (51 400 faults here); glibc's default reuses it (~500)
    faults = map_tasks(local_cluster, _alloc_faults, [()], label=None)[0].value
    assert faults < 200 * 256 // 10


def test_cholmod_starts_no_openmp_team_unless_the_user_says_otherwise():
    # CHOLMOD's supernodal factorization asks for 4 OpenMP threads whatever OMP_NUM_THREADS says;
    # softphantom caps the team with OMP_THREAD_LIMIT (threads counted in /proc after a factorization)
    code = ("import os, softphantom, scipy.sparse as sp; from softphantom.fem import SparseSolver; "
            "T = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(8, 8)); I = sp.identity(8); "
            "SparseSolver('cholmod').factorize((sp.kron(sp.kron(T, I), I) + sp.kron(sp.kron(I, T), I) "
            "+ sp.kron(sp.kron(I, I), T)).tocsc()); "
            "print(len(os.listdir('/proc/self/task')))")
    pytest.importorskip("sksparse.cholmod")
    env = {k: v for k, v in os.environ.items() if not k.startswith("OMP_")}
    run = lambda: int(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,  # noqa: E731
                                     check=True).stdout)
    assert run() == 1
    env["OMP_THREAD_LIMIT"] = "4"
    assert run() > 1


def test_a_local_cluster_closes_at_once_with_a_worker_still_busy(caplog):
    """Its worker processes are ended, not asked to finish their task: the nanny's own close waited
    4 s and then warned "Worker process still alive after 4.0 seconds, killing" (a Ctrl-C during a
    sweep, the end of the demo)."""
    import logging
    import time

    with caplog.at_level(logging.WARNING):
        with dask_client(n_workers=1) as client:
            pids = list(client.run(os.getpid).values())
            client.submit(time.sleep, 60, pure=False)
            time.sleep(0.5)  # the worker is in its task
    assert "still alive" not in caplog.text
    time.sleep(0.2)
    for pid in pids:
        assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"
