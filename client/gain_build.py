"""Building a device's gain table ahead of a session: every cell of the shipped grid, into a file.

A session renders designed, verified gains from its first contact only where its gain table
already holds the contact's cell (docs/gains.md, "Shipped tables"); a cell it lacks is designed
during the contact, and the hand feels interim or fallback gains until the design arrives. The
built-in simulated profiles ship a table (``haptic gains-table --ship``); any other device (a
generic HID profile, a vendor backend) builds the same grid
(:data:`shared.gains.table_file.SHIP_GRID`) for its own limits into this machine's cache of
designs (:mod:`client.gain_store`) once: ``haptic client`` before it joins
(:func:`plan_device_build`, :func:`build_device_table`), or ``haptic gains-table --cache``.

:func:`build_table` is the build itself (both uses, and the shipped tables): the cells are
designed in worker processes (``nice`` 5, one BLAS thread each, Ctrl-C ignored: the parent
stops them), the file is rewritten every :data:`WRITE_EVERY` cells and when the build ends or
is interrupted, so an interrupted build keeps what it designed and the next one goes on. A cell
with no stable design is remembered beside the cache (:func:`undesignable_path`) so that a
device's next run does not try it again.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import os
import sys
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from haptic_collab.client.gain_store import cache_path, preload
from haptic_collab.client.workers import check_worker, stop_pool
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey, Mode
from haptic_collab.shared.gains.policy import K_O_GRID_RATIO
from haptic_collab.shared.gains.table import GainTable, design_cell_modes
from haptic_collab.shared.gains.table_file import (
    SHIP_GRID,
    design_code_hash,
    key_record,
    load_table_document,
    ship_jobs,
    table_document,
)

log = logging.getLogger(__name__)

#: The grid ``haptic client`` builds for a device that has no table (the shipped tables' grid;
#: read when the build is planned, so a test may replace it with a smaller one).
DEVICE_GRID: dict[str, Any] = SHIP_GRID

#: The file of a build is rewritten after this many designed cells (and at its end).
WRITE_EVERY = 20

#: The environment variable that turns the build before joining off when ``0`` (the default of
#: ``ClientOptions.gain_build`` and of ``haptic client``; the test suite sets it).
GAIN_BUILD_ENV = "HAPTIC_GAIN_BUILD"

Job = tuple[GainKey, int]


def gain_build_default() -> bool:
    """Whether a client builds its device's missing gain table before joining, unless told:
    True but where ``$HAPTIC_GAIN_BUILD`` is ``0``, ``no``, ``false`` or ``off``."""
    value = os.environ.get(GAIN_BUILD_ENV, "").strip().lower()
    return value not in ("0", "no", "false", "off")


def _design_job(job: Job) -> tuple[GainKey, int, dict[Mode, GainDesign] | None]:
    """One cell's designs, P and PI (a worker's job); None where it has no stable design."""
    key, cell = job
    try:
        out = design_cell_modes(key, cell, K_O_GRID_RATIO, DEFAULT_HAND_BOX, ("p", "pi"))
    except ValueError:  # no stable gains for this cell: the session designs (and reports) it
        return key, cell, None
    return key, cell, dict(out)


def build_worker() -> None:
    """A build worker's initializer: one BLAS thread, Ctrl-C ignored (the parent stops the
    workers and writes what they made), dies with its parent
    (:func:`client.workers.check_worker`), then ``nice`` 5: a build runs beside other work."""
    check_worker()
    try:
        os.nice(5)
    except OSError:  # not permitted here: run at the normal priority
        pass


def _job_id(job: Job) -> str:
    key, cell = job
    return json.dumps([key_record(key), cell], sort_keys=True)


def undesignable_path(out: Path) -> Path:
    """The file beside a build's file ``out`` listing the jobs found to have no stable design."""
    return out.with_name(out.stem + ".undesignable.json")


def read_undesignable(out: Path) -> set[str]:
    """The jobs :func:`build_table` found without a stable design for the file ``out`` (their
    ids); empty if none were recorded or the record cannot be read."""
    try:
        ids = json.loads(undesignable_path(out).read_text("utf-8"))
    except (OSError, ValueError):
        return set()
    return {i for i in ids if isinstance(i, str)} if isinstance(ids, list) else set()


def _write(out: Path, table: GainTable, code: str, undesignable: set[str]) -> None:
    """Write ``table`` to ``out`` atomically, merged with what the file holds now (another
    client may have added designs meanwhile), and the undesignable jobs beside it."""
    if out.exists():
        try:
            load_table_document(table, json.loads(out.read_text("utf-8")), code)
        except (OSError, ValueError):  # another code or torn: this build's table replaces it
            pass
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f"{out.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(table_document(table, code), separators=(",", ":")) + "\n")
    tmp.replace(out)
    if undesignable:
        side = undesignable_path(out)
        tmp = side.with_name(f"{side.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(sorted(undesignable)) + "\n")
        tmp.replace(side)


def _pool_context() -> multiprocessing.context.BaseContext:
    """Fork while this process has one thread (the workers start at once), else spawn: forking a
    process whose other threads may hold locks is unsafe (as :class:`client.link.DesignWorkers`)."""
    fork = threading.active_count() == 1 and "fork" in multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if fork else "spawn")


def build_table(
    profile: str,
    k_h_max: float,
    b_h_max: float,
    *,
    out: Path,
    workers: int = 1,
    max_jobs: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    grid: dict[str, Any] = SHIP_GRID,
    jobs: Iterable[Job] | None = None,
    stop: threading.Event | None = None,
    remember_undesignable: bool = False,
) -> tuple[int, int]:
    """Design the cells of the grid the file ``out`` lacks, for a device of these limits, and
    write them to it.

    Parameters
    ----------
    profile : str
        The device's name, for a message about a file that cannot be read.
    k_h_max, b_h_max : float
        The device's K_h limit [N/m] and B_h limit [N*s/m] (as the session's gain keys carry
        them: capped to the protocol's ranges).
    out : Path
        The table's file (a shipped table, or the client's cache, :func:`client.gain_store.
        cache_path`): its cells are kept (a file of other design code is started afresh).
    workers : int
        Worker processes.
    max_jobs : int, optional
        Design at most this many cells now (the next build goes on).
    progress : callable, optional
        ``progress(done, total)`` after each cell, and once with ``done`` 0 at the start.
    grid : dict
        The grid (:data:`shared.gains.table_file.SHIP_GRID`'s fields).
    jobs : iterable of (GainKey, int), optional
        Only these jobs of the grid (default: all of :func:`shared.gains.table_file.ship_jobs`).
    stop : threading.Event, optional
        Set to stop the build: the running designs are abandoned (their workers terminated),
        what was designed is written.
    remember_undesignable : bool
        Record the jobs without a stable design beside ``out`` (:func:`undesignable_path`) and
        skip those recorded: a client's cache; not a shipped table (its folder is package data).

    Returns
    -------
    tuple of int
        (jobs finished now, jobs left): a job is a cell of the grid, its P and PI designs;
        a job with no stable design is finished too.

    Raises
    ------
    KeyboardInterrupt
        Ctrl-C: what was designed is written first.
    OSError
        ``out`` cannot be written.
    """
    code = design_code_hash()
    table = GainTable()
    if out.exists():
        try:
            load_table_document(table, json.loads(out.read_text()), code)
        except ValueError as exc:
            print(f"{out}: starting afresh ({exc})", file=sys.stderr)
            table = GainTable()
    undesignable = read_undesignable(out) if remember_undesignable else set()
    wanted = ship_jobs(k_h_max, b_h_max, grid) if jobs is None else list(jobs)
    todo_all = [
        j
        for j in wanted
        if _job_id(j) not in undesignable
        and not (table.has(j[0], j[1]) and table.has(replace(j[0], mode="pi"), j[1]))
    ]
    todo = todo_all if max_jobs is None else todo_all[:max_jobs]
    done = 0
    if progress:
        progress(0, len(todo))
    if not todo:
        return 0, 0
    _write(out, table, code, undesignable)  # a file that cannot be written fails now, not later
    pool = ProcessPoolExecutor(
        max_workers=workers, mp_context=_pool_context(), initializer=build_worker
    )
    finished_cleanly = False
    try:
        pending: set[Future[Any]] = set()
        it = iter(todo)
        for job in it:
            pending.add(pool.submit(_design_job, job))
            if len(pending) >= 2 * workers:
                break
        while pending and not (stop is not None and stop.is_set()):
            finished, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
            for f in finished:
                key, cell, designs = f.result()
                if designs is None and remember_undesignable:
                    undesignable.add(_job_id((key, cell)))
                for mode, d in (designs or {}).items():
                    table.store(replace(key, mode=mode), cell, d)
                done += 1
                if progress:
                    progress(done, len(todo))
                if done % WRITE_EVERY == 0:
                    _write(out, table, code, undesignable)
                nxt = None if stop is not None and stop.is_set() else next(it, None)
                if nxt is not None:
                    pending.add(pool.submit(_design_job, nxt))
        finished_cleanly = True
    finally:
        # stopped, Ctrl-C or a failure: the designs under way are abandoned, at once
        if finished_cleanly:
            pool.shutdown(wait=True)
        else:
            stop_pool(pool)
        _write(out, table, code, undesignable)
    return done, len(todo_all) - done


def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    s = int(round(seconds))
    return f"{s // 60}:{s % 60:02d}" if s >= 60 else f"{s} s"


def progress_bar(
    label: str, stream: Any = None, clock: Callable[[], float] = time.monotonic
) -> Callable[[int, int], None]:
    """A one-line progress bar for :func:`build_table`: ``label [###   ] done/total cells, ETA``
    rewritten in place (``\\r``) on ``stream`` (default stderr), ended by a newline when the
    build is done. The ETA [s, or min:s] is the mean time per cell so far times the cells left."""
    t0 = clock()

    def show(done: int, total: int) -> None:
        out = sys.stderr if stream is None else stream
        frac = done / max(total, 1)
        left = (clock() - t0) / done * (total - done) if done else math.inf
        bar = "#" * int(30 * frac)
        eta = "done" if done == total else f"ETA {_duration(left)}"
        print(f"\r{label} [{bar:<30}] {done}/{total} cells, {eta}", end="", file=out, flush=True)
        if done == total:
            print(file=out, flush=True)

    return show


@dataclass(frozen=True)
class DeviceBuild:
    """What a device lacks of the grid (:func:`plan_device_build`).

    Attributes
    ----------
    k_h_max, b_h_max : float
        The device's limits as the session's gain keys carry them [N/m, N*s/m].
    jobs : list of (GainKey, int)
        The grid's cells neither the shipped tables nor the cache hold (nor are known to have
        no stable design).
    total : int
        The grid's cells for this device.
    out : Path
        The cache file the build writes (:func:`client.gain_store.cache_path`).
    """

    k_h_max: float
    b_h_max: float
    jobs: list[Job]
    total: int
    out: Path


def plan_device_build(
    k_h_max: float, b_h_max: float, grid: dict[str, Any] | None = None
) -> DeviceBuild:
    """The cells of ``grid`` (default :data:`DEVICE_GRID`) a device of these limits [N/m, N*s/m]
    lacks: those neither in the shipped tables nor in this machine's cache
    (:func:`client.gain_store.preload`), both local models. Reads files, designs nothing."""
    grid = DEVICE_GRID if grid is None else grid
    table = GainTable()
    code = str(preload(table, cache=True)["design_code"])
    out = cache_path(code)
    skip = read_undesignable(out)
    every = ship_jobs(k_h_max, b_h_max, grid)
    jobs = [
        (k, c)
        for k, c in every
        if _job_id((k, c)) not in skip
        and not (table.has(k, c) and table.has(replace(k, mode="pi"), c))
    ]
    return DeviceBuild(k_h_max, b_h_max, jobs, len(every), out)


def build_workers() -> int:
    """All the cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def build_device_table(
    plan: DeviceBuild,
    *,
    grid: dict[str, Any] | None = None,
    workers: int | None = None,
    stop: threading.Event | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[int, int]:
    """Design ``plan``'s cells into the cache (:func:`build_table`, on every core unless
    ``workers``); returns (cells finished, cells left: > 0 when stopped)."""
    return build_table(
        f"K_h<={plan.k_h_max:g} B_h<={plan.b_h_max:g}",
        plan.k_h_max,
        plan.b_h_max,
        out=plan.out,
        workers=workers or build_workers(),
        progress=progress,
        grid=DEVICE_GRID if grid is None else grid,
        jobs=plan.jobs,
        stop=stop,
        remember_undesignable=True,
    )
