"""Worker processes that never hold up a stop: the gain-design pools of the client and the server
(whose gain advisor runs the Python client's design, :mod:`server.gains`).

A :class:`concurrent.futures.ProcessPoolExecutor` cannot cancel a job a worker has started, and
``shutdown(wait=False, cancel_futures=True)`` only drops the queued ones: at interpreter exit
Python still joins the pool's management thread, which waits for the running job. A PI design
takes seconds (tens on a busy machine), so Ctrl-C on a server, or the end of a client, waited for
it: 8.5 s in a loaded test run, where the link-loss test saw the server still answering long
after it was told to stop. :func:`stop_pool` drops the queue and terminates the workers, so the
process exits at once; a design cut off this way is simply never delivered.

:func:`timed` runs a gain design and stamps the wall time it took (``design_ms``): the design
code in :mod:`shared` reads no clock.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import Executor, ProcessPoolExecutor
from typing import Any

from haptic_collab.shared.gains.design import GainDesign


def timed(design: Callable[..., GainDesign], *args: Any, **kwargs: Any) -> GainDesign:
    """``design(*args, **kwargs)`` with its ``design_ms`` set to the wall time the call took [ms].

    Module-level, so that a process pool can run it: ``executor.submit(timed, design_cell, key,
    cell, ...)`` measures in the worker.
    """
    t0 = time.perf_counter()
    result = design(*args, **kwargs)
    return dataclasses.replace(result, design_ms=(time.perf_counter() - t0) * 1e3)


def stop_pool(executor: Executor) -> None:
    """Shut ``executor`` down without waiting; terminate a process pool's running workers.

    Uses ``ProcessPoolExecutor.terminate_workers`` where Python has it (3.14), else terminates
    the processes CPython's pool keeps in ``_processes``. Other executors are shut down without
    waiting. Never raises.
    """
    procs = []
    if isinstance(executor, ProcessPoolExecutor):
        procs = list((getattr(executor, "_processes", None) or {}).values())
    executor.shutdown(wait=False, cancel_futures=True)
    terminate = getattr(executor, "terminate_workers", None)
    if callable(terminate):
        try:
            terminate()
        except Exception:  # noqa: BLE001 - a pool already gone: nothing to stop
            pass
        return
    for p in procs:
        try:
            if p.is_alive():
                p.terminate()
        except (OSError, ValueError, AttributeError):  # already reaped or closed
            pass


def background_worker() -> None:
    """Initializer of a design worker process: lowest useful priority (``nice`` 10), one BLAS
    thread, so designs never take CPU from the simulation loop on this machine; the worker dies
    with its parent."""
    import os

    check_worker()
    try:
        os.nice(10)
    except (AttributeError, OSError):  # not on this platform: run at normal priority
        pass


def check_worker() -> None:
    """Initializer of a client's interim-check worker: one BLAS thread, dies with its parent, at
    normal priority: a contact renders conservative unverified gains until its check is done,
    so the check must not yield to the designs (niced, :func:`background_worker`)."""
    import gc
    import os
    import signal

    gc.freeze()  # a forked worker: what it inherited is never scanned (nor copied by the scan)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    # Ctrl-C reaches the whole process group: the parent stops its workers itself (stop_pool);
    # a forked worker must not answer it with its parent's asyncio handler or wake-up fd
    try:
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread (a thread pool standing in for a worker)
        pass
    die_with_parent()


def die_with_parent() -> None:
    """Linux: have the kernel send this worker SIGTERM when its parent dies (``prctl``), so a
    server or client that is killed leaves no design worker behind; elsewhere a no-op."""
    import ctypes
    import os
    import signal
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    import multiprocessing

    parent = multiprocessing.parent_process()
    if parent is not None and os.getppid() != parent.pid:  # it died before the prctl took effect
        os._exit(0)
