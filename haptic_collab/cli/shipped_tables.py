"""``haptic gains-table --ship``: the gain tables shipped for the built-in device profiles.

A session renders designed, verified gains from its first contact when its table already holds
the cell (``shared/gains/tables/<profile>.json``, loaded by the client and the server's gain
advisor): the designs are made here, offline, not during a session (docs/gains.md, "Shipped
tables"). What a table covers is :data:`SHIP_GRID`; a key outside it is designed during the
session as before. The build resumes: cells already in the file are kept, so it can be run in
parts (``--max-jobs``).
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import replace
from pathlib import Path
from typing import Any

from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey, Mode
from haptic_collab.shared.gains.policy import K_O_GRID_RATIO
from haptic_collab.shared.gains.table import GainTable, design_cell_modes
from haptic_collab.shared.gains.table_file import (
    SHIP_GRID,
    design_code_hash,
    load_table_document,
    ship_jobs,
    table_document,
)

#: The built-in profiles that get a shipped table (client.devices.profiles.SIM_PROFILES).
SHIP_PROFILES = ("phantom-desktop", "touch")


def shipped_dir() -> Path:
    """The folder of the shipped tables: ``tables/`` of :mod:`haptic_collab.shared.gains`."""
    import haptic_collab.shared.gains as gains

    return Path(gains.__file__).resolve().parent / "tables"


def _design_job(job: tuple[GainKey, int]) -> tuple[GainKey, int, dict[Mode, GainDesign] | None]:
    key, cell = job
    try:
        out = design_cell_modes(key, cell, K_O_GRID_RATIO, DEFAULT_HAND_BOX, ("p", "pi"))
    except ValueError:  # no stable gains for this cell: the session designs (and reports) it
        return key, cell, None
    return key, cell, dict(out)


def _lower_priority() -> None:
    """A build worker's initializer: ``nice`` 5, one BLAS thread (a build runs beside other work)."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    try:
        os.nice(5)
    except OSError:  # not permitted here: run at the normal priority
        pass


def _write(path: Path, table: GainTable, code: str) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(table_document(table, code), separators=(",", ":")) + "\n")
    tmp.replace(path)


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
) -> tuple[int, int]:
    """Design the cells of :func:`ship_jobs` the file ``out`` lacks and write it; returns
    (cells designed now, jobs left). Writes every 20 jobs, so an interrupted build keeps them."""
    code = design_code_hash()
    table = GainTable()
    if out.exists():
        try:
            load_table_document(table, json.loads(out.read_text()), code)
        except ValueError as exc:
            print(f"{out}: starting afresh ({exc})", file=sys.stderr)
            table = GainTable()
    jobs = [
        (k, c)
        for k, c in ship_jobs(k_h_max, b_h_max, grid)
        if not (table.has(k, c) and table.has(replace(k, mode="pi"), c))
    ]
    todo = jobs if max_jobs is None else jobs[:max_jobs]
    done = 0
    with ProcessPoolExecutor(max_workers=workers, initializer=_lower_priority) as pool:
        pending: set[Future[Any]] = set()
        it = iter(todo)
        for job in it:
            pending.add(pool.submit(_design_job, job))
            if len(pending) >= 2 * workers:
                break
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in finished:
                key, cell, designs = f.result()
                for mode, d in (designs or {}).items():
                    table.store(replace(key, mode=mode), cell, d)
                done += 1
                if progress:
                    progress(done, len(todo))
                if done % 20 == 0:
                    _write(out, table, code)
                nxt = next(it, None)
                if nxt is not None:
                    pending.add(pool.submit(_design_job, nxt))
    _write(out, table, code)
    return done, len(jobs) - done


def progress_bar(label: str) -> Callable[[int, int], None]:
    """A one-line progress bar on stderr for :func:`build_table`."""
    t0 = time.monotonic()

    def show(done: int, total: int) -> None:
        frac = done / max(total, 1)
        eta = (time.monotonic() - t0) / max(done, 1) * (total - done)
        bar = "#" * int(30 * frac)
        print(f"\r{label} [{bar:<30}] {done}/{total} ~{eta:.0f} s left", end="", file=sys.stderr)
        if done == total:
            print(file=sys.stderr)

    return show


if __name__ == "__main__":  # a build without the CLI: python -m haptic_collab.cli.shipped_tables
    from haptic_collab.client.devices.profiles import get_sim_profile

    for name in sys.argv[1:] or SHIP_PROFILES:
        lim = get_sim_profile(name).limits
        n, left = build_table(
            name,
            lim.max_stiffness_n_per_m,
            lim.max_damping_n_s_per_m,
            out=shipped_dir() / f"{name}.json",
            workers=int(os.environ.get("SHIP_WORKERS", "1")),
            progress=progress_bar(name),
        )
        print(f"{name}: {n} designed, {left} left", file=sys.stderr)
