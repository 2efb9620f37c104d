"""The shipped gain tables (``shared/gains/tables/<profile>.json``) against the design code.

A shipped table holds only for the design code of its hash
(:func:`shared.gains.table_file.design_code_hash`). ``--check`` fails when a built-in profile of
:data:`haptic_collab.cli.shipped_tables.SHIP_PROFILES` has no table or one of other code, and
says how many of its grid's cells are missing (a cell with no stable design is never in it);
without ``--check`` the stale or missing tables are built (``haptic gains-table --ship``:
minutes per profile on 2 cores). The same for each table's damping coverage (``b_o_covered``,
:mod:`shared.gains.damping_cover`): stale when made by another check code or lattice
(:func:`shared.gains.table_file.cover_code_hash`) or missing on a cell; rebuilt with
``python -m haptic_collab.cli.shipped_tables --cover`` (about 20 minutes on 2 cores).
"""

from __future__ import annotations

import json
import sys
from typing import Any

from haptic_collab.cli.shipped_tables import (
    SHIP_PROFILES,
    build_table,
    cover_shipped,
    progress_bar,
    ship_jobs,
    shipped_dir,
)
from haptic_collab.client.devices.profiles import get_sim_profile
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.table_file import (
    cover_code_hash,
    cover_is_fresh,
    design_code_hash,
    load_table_document,
)


def stale_tables() -> list[str]:
    """The built-in profiles whose shipped table is missing or of other design code, with why."""
    code = design_code_hash()
    out = []
    for name in SHIP_PROFILES:
        path = shipped_dir() / f"{name}.json"
        if not path.is_file():
            out.append(f"{name}: no shipped table ({path})")
            continue
        table = GainTable()
        try:
            load_table_document(table, json.loads(path.read_text("utf-8")), code)
        except ValueError as exc:
            out.append(f"{name}: {exc}")
            continue
        lim = get_sim_profile(name).limits
        jobs = ship_jobs(lim.max_stiffness_n_per_m, lim.max_damping_n_s_per_m)
        missing = sum(1 for k, c in jobs if not table.has(k, c))
        if missing:
            print(
                f"{name}: {missing} of {len(jobs)} cells without a stable design", file=sys.stderr
            )
        why = stale_cover(json.loads(path.read_text("utf-8")))
        if why:
            out.append(f"{name}: {why}")
    return out


def stale_cover(doc: dict[str, Any]) -> str:
    """Why ``doc``'s damping coverage (``b_o_covered``, :mod:`shared.gains.damping_cover`) is not
    fresh: made by another check code or lattice (:func:`cover_code_hash`), or missing on some
    cells; ``""`` when fresh."""
    if not cover_is_fresh(doc, cover_code_hash()):
        head = doc.get("damping_cover")
        code = head.get("code") if isinstance(head, dict) else None
        return f"damping coverage of cover code {code!r}, this code is {cover_code_hash()!r}"
    missing = sum(1 for rec in doc.get("cells", []) if "b_o_covered" not in rec)
    return f"damping coverage missing on {missing} cells" if missing else ""


def main(args: list[str]) -> int:
    """``--check``: 1 when a shipped table is stale; otherwise rebuild the stale ones."""
    stale = stale_tables()
    if "--check" in args:
        for line in stale:
            fix = (
                "python -m haptic_collab.cli.shipped_tables --cover"
                if "damping coverage" in line
                else "haptic gains-table --ship"
            )
            print(f"stale gain table: {line}; run `{fix}`", file=sys.stderr)
        return 1 if stale else 0
    for line in stale:
        name = line.split(":", 1)[0]
        lim = get_sim_profile(name).limits
        build_table(
            name,
            lim.max_stiffness_n_per_m,
            lim.max_damping_n_s_per_m,
            out=shipped_dir() / f"{name}.json",
            workers=2,
            progress=progress_bar(name),
        )
    if stale:  # the designs' coverage of object damping, for the designs as they are now
        cover_shipped(workers=2, progress=progress_bar("damping coverage"))
    return 0
