"""``haptic gains-table --ship``: the gain tables shipped for the built-in device profiles.

A session renders designed, verified gains from its first contact when its table already holds
the cell (``shared/gains/tables/<profile>.json``, loaded by the client and the server's gain
advisor): the designs are made here, offline, not during a session (docs/gains.md, "Shipped
tables"). What a table covers is :data:`SHIP_GRID`; a key outside it is designed during the
session as before. The build resumes: cells already in the file are kept, so it can be run in
parts (``--max-jobs``).

The build itself (:func:`build_table`, :func:`progress_bar`) is the client's
(:mod:`client.gain_build`): a client whose device has no shipped table builds the same grid
into its cache before it joins, and runtime code does not import the CLI.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from haptic_collab.client.gain_build import build_table, progress_bar
from haptic_collab.shared.gains.table_file import SHIP_GRID, ship_jobs

__all__ = ["SHIP_GRID", "SHIP_PROFILES", "build_table", "progress_bar", "ship_jobs", "shipped_dir"]

#: The built-in profiles that get a shipped table (client.devices.profiles.SIM_PROFILES).
SHIP_PROFILES = ("phantom-desktop", "touch")


def shipped_dir() -> Path:
    """The folder of the shipped tables: ``tables/`` of :mod:`haptic_collab.shared.gains`."""
    import haptic_collab.shared.gains as gains

    return Path(gains.__file__).resolve().parent / "tables"


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
