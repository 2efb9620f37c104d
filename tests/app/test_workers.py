"""A stop never waits for a running gain design: the pool's workers are terminated."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from dataclasses import replace

SCRIPT = textwrap.dedent(
    """
    import multiprocessing, sys, time
    from concurrent.futures import ProcessPoolExecutor
    from haptic_collab.client.workers import stop_pool

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


def test_timed_stamps_the_design_with_the_wall_time_it_took():
    from haptic_collab.client.workers import timed
    from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
    from haptic_collab.shared.gains.key import GainKey
    from haptic_collab.shared.gains.table import design_cell

    key = GainKey(1000.0, 20.0, 0, "p", 0.15, 1000.0, 10.0)
    plain = design_cell(key, 20, 2.0**0.25, DEFAULT_HAND_BOX)
    assert plain.design_ms == 0.0  # the design itself reads no clock
    t0 = time.perf_counter()
    stamped = timed(design_cell, key, 20, 2.0**0.25, DEFAULT_HAND_BOX)
    took_ms = (time.perf_counter() - t0) * 1e3
    assert 0.0 < stamped.design_ms <= took_ms
    assert replace(stamped, design_ms=0.0) == plain  # the same gains
