"""Building a shipped gain table (haptic_collab.cli.shipped_tables): what the client then loads
is the design the session would have made, and an interrupted build resumes."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from haptic_collab.cli.shipped_tables import SHIP_GRID, build_table, ship_jobs
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.table_file import design_code_hash, load_table_document

# two cells at 100 Hz (N = 10: a design's loop is a fifth of 20 Hz's), one tick of delay
TINY = {
    **SHIP_GRID,
    "sim_rate_hz": (100.0,),
    "delay_ticks": (1,),
    "stiff_ratio": (1.0,),
    "k_o_n_per_m": (300.0, 330.0),
}


@pytest.mark.slow  # designs four cells afresh in a worker: a minute on a fresh checkout
def test_a_built_table_holds_the_sessions_own_designs_and_a_second_build_resumes(tmp_path) -> None:
    out = tmp_path / "phantom.json"
    jobs = ship_jobs(1000.0, 10.0, TINY)
    assert len(jobs) == 2  # the cells of 300 and 330 N/m, each designing P and PI
    done, left = build_table("phantom", 1000.0, 10.0, out=out, workers=1, grid=TINY, max_jobs=1)
    assert (done, left) == (1, 1)
    done, left = build_table("phantom", 1000.0, 10.0, out=out, workers=1, grid=TINY)
    assert (done, left) == (1, 0)  # only the missing cell
    table = GainTable()
    assert load_table_document(table, json.loads(out.read_text()), design_code_hash()) == 4
    for key, cell in jobs:
        for mode in ("p", "pi"):
            mkey = replace(key, mode=mode)
            k_o = table.grid_point(cell) * 1.05
            assert table.lookup(mkey, k_o) == GainTable().design(mkey, k_o)  # the same design
