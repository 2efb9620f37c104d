"""A stop never waits for a running gain design: the pool's workers are terminated."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import multiprocessing, sys, time
    from concurrent.futures import ProcessPoolExecutor
    from haptic_collab.workers import stop_pool

    def design():  # stands for a PI design on a busy machine
        time.sleep(300.0)

    if __name__ == "__main__":
        pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        running = pool.submit(design)
        pool.submit(design)  # and one waiting behind it
        while not running.running():
            time.sleep(0.01)
        worker = next(iter(pool._processes.values()))
        print(worker.pid, flush=True)
        stop_pool(pool)
    """
)


def test_a_process_exits_without_waiting_for_its_running_design(tmp_path):
    script = tmp_path / "stop.py"
    script.write_text(SCRIPT)
    # without stop_pool the interpreter's exit would join the pool and wait out the 300 s job
    res = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert res.returncode == 0, res.stderr
    worker = int(res.stdout.split()[0])
    try:  # the worker is gone, not orphaned
        os.kill(worker, 0)
    except ProcessLookupError:
        pass
    else:
        raise AssertionError(f"design worker {worker} still running")
