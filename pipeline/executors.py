"""Executors: where tasks run. All share submit / wait / close.

inline   in this process, one at a time (default; best for debugging)
process  a local pool of spawned processes (never forked: h5py state must not be copied)
dask     a dask.distributed cluster (--address tcp://...), or a LocalCluster when no address
"""
from __future__ import annotations

import concurrent.futures as cf
import os
import signal
import sys
import threading
import time
from typing import Callable

from pipeline.errors import PipelineError


class InlineExecutor:
    """submit(fn, task, priority) runs or queues a task; `slots`: how many run at once (the
    scheduler hands over no more than that, choosing which itself; None: the executor queues
    every task it is given and orders them by `priority`, higher first)."""
    name = "inline"
    slots: int | None = 1

    def submit(self, fn: Callable, task: dict, priority: int = 0):
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(fn(task))
        except BaseException as exc:  # noqa: BLE001 - re-raised by result()
            fut.set_exception(exc)
        return fut

    def wait(self, futures):
        return set(futures)

    def result(self, fut):
        return fut.result()

    def close(self, interrupted: bool = False):
        pass


THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def worker_threads(jobs: int) -> int:
    """Threads each of `jobs` workers may use so that together they fill, not oversubscribe, the CPU."""
    return max(1, (os.cpu_count() or 1) // max(1, jobs))


def _limit_threads(n: int) -> None:
    """Pool initializer: cap OpenMP/BLAS threads before any numeric library is imported.

    Spinning OpenMP threads of several workers on shared cores slow each other down many times
    over; a value the user set explicitly is kept."""
    for var in THREAD_VARS:
        os.environ.setdefault(var, str(n))


PARENT_POLL_S = 1.0


def _init_worker(threads: int, parent: int) -> None:
    _limit_threads(threads)
    _exit_with_parent(parent)


def _exit_with_parent(parent: int) -> None:
    """A worker whose parent was killed (SIGKILL, the OOM killer) would compute on, orphaned,
    holding its memory: it keeps its own end of the task queue's pipe open, so it never reads
    the parent's end closing.  Linux ends it with its parent (PR_SET_PDEATHSIG); elsewhere, and
    should that fail, a thread watching the parent ends it within PARENT_POLL_S."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)       # 1: PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:          # died before the line above took effect
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent,), name="watch-parent", daemon=True).start()


def _watch_parent(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(PARENT_POLL_S)
    os._exit(1)


class ProcessExecutor(InlineExecutor):
    name = "process"

    def __init__(self, jobs: int):
        import multiprocessing as mp
        self.slots = max(1, int(jobs))
        self.pool = cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                                           initializer=_init_worker,
                                           initargs=(worker_threads(jobs), os.getpid()))

    def submit(self, fn, task, priority: int = 0):
        return self.pool.submit(fn, task)

    def wait(self, futures):
        done, _ = cf.wait(futures, return_when=cf.FIRST_COMPLETED)
        return done

    def close(self, interrupted: bool = False):
        """Wait for the running tasks; `interrupted` (Ctrl-C, SIGTERM): stop the workers now.
        A worker stopped mid-task leaves only its temp file (gc removes it) and, for training,
        its checkpoint, from which the next run resumes."""
        if interrupted:
            for proc in list((getattr(self.pool, "_processes", None) or {}).values()):
                proc.terminate()
        self.pool.shutdown(wait=not interrupted, cancel_futures=True)


class DaskExecutor(InlineExecutor):
    name = "dask"
    slots = None            # the cluster's scheduler places tasks, by their priority

    def __init__(self, address: str | None, jobs: int):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise PipelineError("the dask executor needs dask.distributed (pip install 'dask[distributed]')") from None
        self._cluster = None
        try:
            if address:
                self.client = Client(address, timeout="10s")
            else:
                self._cluster = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True,
                                             dashboard_address=None)
                self.client = Client(self._cluster)
        except (OSError, TimeoutError, ValueError) as exc:
            raise PipelineError(f"cannot reach Dask scheduler at {address}: {exc}") from None

    def submit(self, fn, task, priority: int = 0):
        return self.client.submit(fn, task, pure=False, key=f"{task['instance']}-{task['key'][:8]}",
                                  priority=int(priority))

    def wait(self, futures):
        from distributed import wait
        done, _ = wait(list(futures), return_when="FIRST_COMPLETED")
        return set(done)

    def result(self, fut):
        return fut.result()

    def close(self, interrupted: bool = False):
        self.client.close()     # releases the futures: tasks not yet started are dropped
        if self._cluster is not None:
            self._cluster.close()


def make_executor(name: str, jobs: int = 1, address: str | None = None):
    if name == "inline":
        return InlineExecutor()
    if name == "process":
        return ProcessExecutor(max(1, jobs))
    if name == "dask":
        return DaskExecutor(address, max(1, jobs))
    raise PipelineError(f"unknown executor '{name}' (inline, process, dask)")
