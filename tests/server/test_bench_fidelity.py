"""``haptic bench fidelity`` end to end on a small grid: the JSON a user gets, and the plots."""

from __future__ import annotations

import json
from pathlib import Path

from haptic_collab.server.bench_fidelity import Grid, plot, run
from haptic_collab.shared.fidelity import SCHEMES
from haptic_collab.shared.full_loop import DEFAULT_HAND, Hand

CELL_KEYS = {
    "scheme", "model", "k_o_n_per_m", "sim_rate_hz", "delay_ms", "hand", "trajectory", "stable",
    "hold_p2p_mm", "peak_penetration_mm", "steady_state_error_mm", "felt_stiffness_ratio_1hz",
    "felt_stiffness_ratio_8hz", "energy_out_mj", "force_ripple_n",
}  # fmt: skip


def test_small_grid_json_summary_and_plots(tmp_path: Path) -> None:
    grid = Grid(
        k_o=(1000.0,),
        sim_rate_hz=(20.0,),
        delay_ms=(0.0, 50.0),
        hands=(DEFAULT_HAND, Hand(0.1, 2.0, 1000.0)),
    )
    out = run(grid=grid, include_3d=False, workers=2)
    json.dumps(out)  # serialisable
    assert out["schemes"] == list(SCHEMES)
    assert set(out["tuning"]) == set(SCHEMES)
    cells = out["cells"]
    assert len(cells) == len(SCHEMES) * 2 * 2 * 3
    for c in cells:
        assert CELL_KEYS <= set(c)
    # the paper's claim on this stiff object: the local models hold, direct rendering does not
    summary = out["summary"]
    assert summary["local-p"]["stable_fraction"] == 1.0
    assert summary["local-pi"]["stable_fraction"] == 1.0
    assert summary["direct"]["stable_fraction"] < 0.5
    for s in SCHEMES:
        assert 0.0 <= summary[s]["best_transparency_fraction"] <= 1.0
    assert 0.0 <= summary["local_model_best_fraction"] <= 1.0
    # a P local model's felt stiffness is below K_o (K_h in series), PI's closer to it
    felt = {c["scheme"]: c["felt_stiffness_ratio_1hz"] for c in cells if c["delay_ms"] == 0.0}
    assert felt["local-p"] is not None and felt["local-pi"] is not None
    assert felt["local-p"] < felt["local-pi"] <= 1.05
    paths = plot(out, tmp_path)
    assert [p.name for p in paths] == ["fidelity-stability.png", "fidelity-transparency.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)
