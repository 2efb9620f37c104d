"""``haptic gains-table --ship``: the gain tables shipped for the built-in device profiles.

A session renders designed, verified gains from its first contact when its table already holds
the cell (``shared/gains/tables/<profile>.json``, loaded by the client and the server's gain
advisor): the designs are made here, offline, not during a session (docs/gains.md, "Shipped
tables"). What a table covers is :data:`SHIP_GRID`; a key outside it is designed during the
session as before. The build resumes: cells already in the file are kept, so it can be run in
parts (``--max-jobs``).

Each table also says, per design, up to which object damping B_o [N/m] the design holds
(``b_o_covered``: :func:`cover_shipped`, checked on the damped loop by
:mod:`shared.gains.damping_cover`; ``python -m haptic_collab.cli.shipped_tables --cover``): a
FEM solid's key (B_o > 0) renders the design for B_o = 0 up to it
(:func:`shared.gains.choose.table_design`).

The build itself (:func:`build_table`, :func:`progress_bar`) is the client's
(:mod:`client.gain_build`): a client whose device has no shipped table builds the same grid
into its cache before it joins, and runtime code does not import the CLI.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from haptic_collab.client.gain_build import (
    _pool_context,
    build_table,
    build_worker,
    progress_bar,
    stop_pool,
)
from haptic_collab.shared.gains.damping_cover import covered_b_o
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.table_file import (
    SHIP_GRID,
    cover_code_hash,
    cover_header,
    cover_is_fresh,
    design_code_hash,
    design_from_record,
    key_from_record,
    ship_jobs,
)

__all__ = ["SHIP_GRID", "SHIP_PROFILES", "build_table", "progress_bar", "ship_jobs", "shipped_dir"]

#: The built-in profiles that get a shipped table (client.devices.profiles.SIM_PROFILES).
SHIP_PROFILES = ("phantom-desktop", "touch")


def shipped_dir() -> Path:
    """The folder of the shipped tables: ``tables/`` of :mod:`haptic_collab.shared.gains`."""
    import haptic_collab.shared.gains as gains

    return Path(gains.__file__).resolve().parent / "tables"


def _cover_one(key: GainKey, cell: int, design: GainDesign) -> float:
    """:func:`shared.gains.damping_cover.covered_b_o` of one shipped design (a worker's job)."""
    t = GainTable()
    return covered_b_o(key, cell, design, t.grid_ratio, t.hand_box)


def _cover_signature(rec: dict[str, Any]) -> str:
    """What a coverage check of a cell record depends on: the key but the device's limits and
    the local model's name (:func:`shared.gains.interim.verify_gains` reads neither), the cell
    and the design. The two profiles' tables share half their designs."""
    key = {k: v for k, v in rec["key"].items() if k not in ("k_h_max", "b_h_max", "mode")}
    return json.dumps([key, rec["cell"], rec["design"]], sort_keys=True)


def cover_shipped(
    names: Sequence[str] = SHIP_PROFILES,
    *,
    workers: int = 1,
    progress: Callable[[int, int], None] | None = None,
    write_every: int = 50,
) -> tuple[int, int]:
    """Add ``b_o_covered`` [N/m] (:func:`shared.gains.damping_cover.covered_b_o`) to every cell
    of the shipped tables of ``names``, in ``workers`` niced worker processes
    (:func:`client.gain_build.build_worker`), and the cover code's hash and lattice to each file
    (``damping_cover``). Resumes: a cell that has a coverage of the current cover code keeps it;
    the files are rewritten every ``write_every`` checks and at the end. The designs are not
    touched. Returns (designs checked now, designs left).

    Raises
    ------
    ValueError
        A shipped table of another design code (build it first: ``haptic gains-table --ship``).
    """
    from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait

    code, cover = design_code_hash(), cover_code_hash()
    docs: dict[str, dict[str, Any]] = {}
    for name in names:
        path = shipped_dir() / f"{name}.json"
        doc = json.loads(path.read_text("utf-8"))
        if doc.get("design_code") != code:
            raise ValueError(f"{path}: designs of another design code; build them first")
        fresh = cover_is_fresh(doc, cover)
        for rec in doc["cells"]:
            if not fresh:
                rec.pop("b_o_covered", None)
        doc["damping_cover"] = cover_header(cover)
        docs[name] = doc
    table = GainTable()
    mid = table.cell(300.0)
    todo: dict[str, list[dict[str, Any]]] = {}
    known: dict[str, float] = {}
    for doc in docs.values():
        for rec in doc["cells"]:
            sig = _cover_signature(rec)
            if "b_o_covered" in rec:
                known[sig] = rec["b_o_covered"]
            else:
                todo.setdefault(sig, []).append(rec)
    for sig, recs in list(todo.items()):  # the other profile's twin was checked already
        if sig in known:
            for rec in recs:
                rec["b_o_covered"] = known[sig]
            del todo[sig]
    # the FEM solid's neighbourhood first (K_o 150-600 N/m, few ticks of delay): a pass cut
    # short covers the cells a demo reaches
    order = sorted(
        todo,
        key=lambda s: (
            abs(todo[s][0]["cell"] - mid) > 7,
            todo[s][0]["key"]["delay_ticks"],
            abs(todo[s][0]["cell"] - mid),
        ),
    )

    def write() -> None:
        for name, doc in docs.items():
            path = shipped_dir() / f"{name}.json"
            tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(doc, indent=None, separators=(",", ":")) + "\n")
            tmp.replace(path)

    done = 0
    if progress:
        progress(0, len(order))
    if not order:
        write()
        return 0, 0
    pool = ProcessPoolExecutor(
        max_workers=workers, mp_context=_pool_context(), initializer=build_worker
    )
    try:
        it = iter(order)
        pending: dict[Future[float], str] = {}

        def submit() -> None:
            sig = next(it, None)
            if sig is not None:
                rec = todo[sig][0]
                key = key_from_record(rec["key"])
                design = design_from_record(rec["design"], table.hand_box)
                pending[pool.submit(_cover_one, key, rec["cell"], design)] = sig

        for _ in range(2 * workers):
            submit()
        while pending:
            finished, _ = wait(list(pending), return_when=FIRST_COMPLETED)
            for f in finished:
                sig = pending.pop(f)
                for rec in todo[sig]:
                    rec["b_o_covered"] = f.result()
                done += 1
                if progress:
                    progress(done, len(order))
                if done % write_every == 0:
                    write()
                submit()
    finally:
        stop_pool(pool)
        write()
    return done, len(order) - done


if __name__ == "__main__":  # a build without the CLI: python -m haptic_collab.cli.shipped_tables
    from haptic_collab.client.devices.profiles import get_sim_profile

    if "--cover" in sys.argv[1:]:  # the damping coverage of the tables as they are
        names = [a for a in sys.argv[1:] if a != "--cover"] or list(SHIP_PROFILES)
        n, left = cover_shipped(
            names,
            workers=int(os.environ.get("SHIP_WORKERS", "2")),
            progress=progress_bar("damping coverage"),
        )
        print(f"damping coverage: {n} designs checked, {left} left", file=sys.stderr)
        sys.exit(0)
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
