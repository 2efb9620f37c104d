"""Worker processes that never hold up a stop: the gain-design pools of the server and client.

A :class:`concurrent.futures.ProcessPoolExecutor` cannot cancel a job a worker has started, and
``shutdown(wait=False, cancel_futures=True)`` only drops the queued ones: at interpreter exit
Python still joins the pool's management thread, which waits for the running job. A PI design
takes seconds (tens on a busy machine), so Ctrl-C on a server, or the end of a client, waited for
it: 8.5 s in a loaded test run, where the link-loss test saw the server still answering long
after it was told to stop. :func:`stop_pool` drops the queue and terminates the workers, so the
process exits at once; a design cut off this way is simply never delivered.
"""

from __future__ import annotations

from concurrent.futures import Executor, ProcessPoolExecutor


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
