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
    # with own-force compensation both local models feel the object's own stiffness at 1 Hz
    # (the paper's P model would feel K_h K_o / (K_h + K_o) < K_o / 2), as direct rendering does
    felt = {c["scheme"]: c["felt_stiffness_ratio_1hz"] for c in cells if c["delay_ms"] == 0.0}
    assert felt["local-p"] is not None and felt["local-pi"] is not None
    assert 0.95 < felt["local-p"] <= 1.05 and 0.95 < felt["local-pi"] <= 1.05
    paths = plot(out, tmp_path)
    assert [p.name for p in paths] == ["fidelity-stability.png", "fidelity-transparency.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_the_hand_box_ranking_asks_for_stability_with_every_hand() -> None:
    from haptic_collab.server.bench_fidelity import _hand_box_ranking

    def cell(scheme: str, hand: int, stable: bool, felt: float, delay: float = 0.0) -> dict:
        return {
            "model": "1d", "scheme": scheme, "k_o_n_per_m": 300.0, "sim_rate_hz": 20.0,
            "delay_ms": delay, "trajectory": "press", "hand": {"mass_kg": hand},
            "stable": stable, "felt_stiffness_ratio_1hz": felt,
        }  # fmt: skip

    cells = [
        # direct renders K_o exactly but is unstable with the second hand: not box-stable
        cell("direct", 1, True, 1.0), cell("direct", 2, False, 1.0),
        cell("local-pi", 1, True, 0.8), cell("local-pi", 2, True, 0.8),
        # at 100 ms nothing but the local model holds with both hands
        cell("direct", 1, False, 1.0, 100.0), cell("direct", 2, False, 1.0, 100.0),
        cell("local-pi", 1, True, 0.7, 100.0), cell("local-pi", 2, True, 0.7, 100.0),
    ]  # fmt: skip
    r = _hand_box_ranking(cells, ["local-pi", "direct"])
    assert r["conditions"] == 2 and r["local_model_best_fraction"] == 1.0
    assert r["schemes"]["direct"] == {
        "box_stable_fraction": 0.0, "best_transparency_fraction_box": 0.0,
    }  # fmt: skip
    assert r["schemes"]["local-pi"]["best_transparency_fraction_box"] == 1.0
    # stable with every hand, direct wins: it is closer to 1
    cells[1]["stable"] = True
    r = _hand_box_ranking(cells, ["local-pi", "direct"])
    assert r["schemes"]["direct"]["best_transparency_fraction_box"] == 0.5
    assert r["local_model_best_fraction"] == 0.5


def test_near_best_counts_what_a_user_could_not_tell_from_the_best() -> None:
    from haptic_collab.server.bench_fidelity import STIFFNESS_JND, summarize

    def cell(scheme: str, k_o: float, stable: bool, felt: float) -> dict:
        return {
            "model": "1d", "scheme": scheme, "k_o_n_per_m": k_o, "sim_rate_hz": 20.0,
            "delay_ms": 0.0, "trajectory": "press", "hand": {"mass_kg": 0.1}, "stable": stable,
            "felt_stiffness_ratio_1hz": felt, "felt_stiffness_ratio_8hz": felt,
            "felt_elastic_ratio_1hz": felt, "hold_p2p_mm": 0.0,
        }  # fmt: skip

    assert STIFFNESS_JND <= 0.15  # never looser than the measured Weber fractions
    cells = [
        # a stable direct renderer is exactly K_o: it is the best; 0.95 K_o is within the JND
        cell("direct", 300.0, True, 1.0), cell("local-pi", 300.0, True, 0.95),
        cell("virtual-coupling", 300.0, True, 0.5),
        # 0.85 K_o is not: a user feels the difference
        cell("direct", 1000.0, True, 1.0), cell("local-pi", 1000.0, True, 0.85),
        # an unstable scheme is never near the best, however stiff
        cell("direct", 3000.0, False, 1.0), cell("local-pi", 3000.0, True, 0.7),
    ]  # fmt: skip
    s = summarize(cells, ["local-pi", "direct", "virtual-coupling"])
    assert s["local_model_best_fraction"] == 1 / 3  # strictly the closest: only at 3000 N/m
    assert s["local_model_near_best_fraction"] == 2 / 3
    assert s["local-pi"]["near_best_fraction"] == 2 / 3
    assert s["direct"]["near_best_fraction"] == 2 / 3
    assert s["virtual-coupling"]["near_best_fraction"] == 0.0
