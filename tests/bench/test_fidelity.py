"""``haptic bench fidelity`` end to end on a small grid: the JSON a user gets, and the plots; the
ranking's rules on conditions with a known answer."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.bench.fidelity import Grid, plot, run
from haptic_collab.research.fidelity_ranking import (
    BAND_HZ,
    STIFFNESS_JND,
    Outcome,
    choose_variant,
    felt_error,
    rank,
    summarize,
)
from haptic_collab.research.fidelity_schemes import SCHEMES, Rendering, peer_renderings
from haptic_collab.shared.felt_stiffness import felt_responses
from haptic_collab.shared.full_loop import DEFAULT_HAND, Hand
from haptic_collab.shared.gains.policy import FELT_BAND_HZ


@pytest.mark.slow  # a fidelity grid run: benchmark-shaped
def test_small_grid_json_summary_and_plots(tmp_path: Path) -> None:
    grid = Grid(
        k_o=(1000.0,),
        sim_rate_hz=(20.0,),
        delay_ms=(0.0, 50.0),
        hands=(DEFAULT_HAND, Hand(0.1, 2.0, 1000.0)),
        objects=("spring", "sls"),
        outside_hands=(Hand(0.3, 0.5, 300.0),),
    )
    out = run(grid=grid, include_3d=False, workers=2)
    json.dumps(out, allow_nan=False)  # serialisable, no NaN
    again = out["felt_probe"]
    assert again["retry_extra_s"] > 0.0 and 0 <= again["read_again"] <= again["measured_again"]
    assert out["schemes"] == list(SCHEMES)
    assert set(out["tuning"]) == set(SCHEMES)
    conds = out["conditions"]
    assert [(c["object"], c["delay_ms"]) for c in conds] == [
        ("spring", 0.0), ("spring", 50.0), ("sls", 0.0), ("sls", 50.0),
    ]  # fmt: skip
    for c in conds:
        assert set(c["schemes"]) == set(SCHEMES)
        for s, r in c["schemes"].items():
            assert len(r["stable_cells"]) == 2 * 3  # box hands x trajectories
            assert len(r["outside_stable"]) == 1 * 3
            assert set(r["felt"]) == {f"{hz:g}" for hz in out["felt_hz"]}
            if not s.startswith("local"):
                # a peer is represented by one of its own tunings
                sweep = peer_renderings(s, k_o=1000.0, sim_rate_hz=20.0)
                assert r["variant"] in {x.variant for x in sweep}
    spring = {c["delay_ms"]: c for c in conds if c["object"] == "spring"}
    # the paper's claim on its design model: the local models hold, direct rendering does not
    for d in (0.0, 50.0):
        assert spring[d]["schemes"]["local-p"]["box_stable"]
        assert spring[d]["schemes"]["local-pi"]["box_stable"]
    assert not spring[50.0]["schemes"]["direct"]["box_stable"]
    # with own-force compensation the local models feel the object's own stiffness at 1 Hz (the
    # device caps K_h at 1000 N/m = K_o; the slow loop carries the rest)
    q = spring[0.0]["schemes"]["local-p"]["felt"]["1"]
    assert q is not None and 0.95 < q[0] < 1.05
    summary = out["summary"]
    for s in SCHEMES:
        assert 0.0 <= summary[s]["box_stable_fraction"] <= 1.0
    # each peer keeps, on every object, the tuning it picked on the spring of the same K_o,
    # rate and delay: the object is not known to it
    by = {(c["object"], c["delay_ms"]): c for c in conds}
    for (_name, d), c in by.items():
        for s, r in c["schemes"].items():
            assert r["variant"] == by[("spring", d)]["schemes"][s]["variant"]
    # the two-user grid, reported apart: every condition again, ranked by how a user held
    # still follows the other's press; static-local's plane, never updated, follows nothing
    two = out["conditions_two_users"]
    assert [(c["object"], c["delay_ms"]) for c in two] == [
        (c["object"], c["delay_ms"]) for c in conds
    ]
    for c in two:
        assert c["schemes"]["static-local"]["felt_error"] is None
        for s, r in c["schemes"].items():
            assert len(r["stable_cells"]) == 2 * 3 and r["outside_stable"] == ""
            if s in ("mmt", "mmt-id"):
                assert r["variant"].endswith(("zoh", "foh"))  # the hold matters: swept
    assert summary["two_users"]["product"]["local_models"] == ["local-p", "local-pi"]
    prod = summary["product"]
    assert prod["local_models"] == ["local-p", "local-pi"]
    assert 0.0 <= prod["near_best_fraction_box_unseen"] <= 1.0
    paths = plot(out, tmp_path)
    assert [p.name for p in paths] == ["fidelity-stability.png", "fidelity-transparency.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)


@pytest.mark.slow  # a fidelity grid run: benchmark-shaped
def test_a_narrower_design_range_is_what_knowing_the_object_would_buy() -> None:
    # the local models' design holds on an object 15 % softer than the bottom of its cell to 25 %
    # stiffer than its top; run with no range beyond the cell (the object known that well) the
    # design is nearly model-mediated teleoperation's plane and is felt as the spring itself,
    # tied with mmt; the product's own design pays for the range with a damper felt over the
    # band, and the product is felt as the spring only through the verified plane it renders
    # once its own-response check has seen the spring (no damper: checked on objects 5 % off)
    grid = Grid(
        k_o=(300.0,),
        sim_rate_hz=(20.0,),
        delay_ms=(0.0,),
        hands=(DEFAULT_HAND, Hand(0.6, 2.0, 20.0)),
        objects=("spring",),
        outside_hands=(),
    )
    schemes = ("local-p", "mmt")
    product = run(grid=grid, schemes=schemes, include_3d=False, workers=1)
    known = run(
        grid=grid, schemes=schemes, include_3d=False, workers=1, design_margin=0.0,
        design_stiffer_by=0.0,
    )  # fmt: skip
    assert product["options"]["design_margin"] == 0.15
    assert product["options"]["design_stiffer_by"] == 0.25
    assert (known["options"]["design_margin"], known["options"]["design_stiffer_by"]) == (0.0, 0.0)
    (g,), (g0,) = known["gains"], product["gains"]
    # the client's gain-table cell is 10 % wide: its design holds over it, scaled to K_o
    assert g["k_h"] == pytest.approx(300.0, rel=0.05)
    assert g["own_gain"] * g["k_h"] == pytest.approx(1.0)
    assert g["b_h"] <= 1.0 < g0["b_h"]
    (c,), (c0,) = known["conditions"], product["conditions"]
    assert c["schemes"]["local-p"]["box_stable"] and c0["schemes"]["local-p"]["box_stable"]
    err, err0 = c["schemes"]["local-p"]["felt_error"], c0["schemes"]["local-p"]["felt_error"]
    assert err < 0.25 * math.log1p(STIFFNESS_JND) and err0 < 0.25 * math.log1p(STIFFNESS_JND)
    assert g0["verified_plane"] is not None and g0["verified_plane"]["b_h"] == 0.0

    def design_error(d: dict[str, Any]) -> float:
        # the design's felt error over the band on the spring, where no plane renders
        q = felt_responses(
            FELT_BAND_HZ, k_o=300.0, k_h=d["k_h"], b_h=d["b_h"], rate_ratio=50, delay_ticks=0,
            proxy_hold=d["proxy_hold"], own_gain=d["own_gain"],
        )[:, 0]  # fmt: skip
        return max(abs(math.log(abs(v) / 300.0)) for v in q)

    known_error, product_error = design_error(g), design_error(g0)
    assert known_error < 0.25 * math.log1p(STIFFNESS_JND) and 3.0 * known_error < product_error
    assert "local-p" in c["near_best"]
    for bad in ({"design_margin": 1.0}, {"design_margin": -0.1}, {"design_stiffer_by": math.nan}):
        with pytest.raises(ValueError, match="design_"):
            run(grid=grid, schemes=schemes, include_3d=False, workers=1, **bad)  # type: ignore[arg-type]
    # a plane rendered before its cell verifies, or a NaN wait, is no option
    assert product["options"]["plane_check_s"] == 0.0
    for wait in (-1.0, math.nan):
        with pytest.raises(ValueError, match="plane_check_s"):
            run(grid=grid, schemes=schemes, include_3d=False, workers=1, plane_check_s=wait)


def _felt(q: float) -> dict[float, tuple[float, float] | None]:
    return {hz: (q, 0.0) for hz in BAND_HZ}


def test_the_felt_error_is_the_worst_of_the_band() -> None:
    f = _felt(1.0)
    assert felt_error(f) == 0.0
    f[8.0] = (1.5, 0.3)
    f[30.0] = (5.0, 0.0)  # above the band: reported, not ranked
    assert felt_error(f) == pytest.approx(math.log(1.5))
    f[0.5] = None  # a limit cycle or an unsettled response cannot be ranked
    assert math.isinf(felt_error(f))


def _rec(box_stable: bool, err: float | None, cells: str = "11") -> dict[str, Any]:
    return {"box_stable": box_stable, "felt_error": err, "stable_cells": cells}


def test_ties_within_the_jnd_and_stability_with_every_hand() -> None:
    assert STIFFNESS_JND <= 0.15  # never looser than the measured Weber fractions
    jnd = math.log1p(STIFFNESS_JND)
    cond: dict[str, Any] = {
        "schemes": {
            # renders the object exactly but is unstable with one hand: not in the box ranking
            "direct": _rec(False, 0.0, "10"),
            "local-pi": _rec(True, 0.9 * jnd),  # within the JND of the best: a tie
            "mmt": _rec(True, 0.0),
            "virtual-coupling": _rec(True, 1.1 * jnd),  # a user would feel it
        }
    }
    rank(cond)
    assert cond["best"] == ["mmt"]
    assert sorted(cond["near_best"]) == ["local-pi", "mmt"]
    # per hand: with the first hand direct is stable and ties for the best
    per = cond["per_hand"]
    assert per["cells"] == 2
    assert per["best"]["direct"] == 1 and per["best"]["mmt"] == 2
    assert per["near_best"]["local-pi"] == 2 and per["near_best"]["virtual-coupling"] == 0


def test_a_peer_is_represented_by_its_best_tuning() -> None:
    r = Rendering("mmt", "mmt")
    unstable_but_close = Outcome(r, stable=[True, False], felt=_felt(1.0))
    stable_far = Outcome(r, stable=[True, True], felt=_felt(0.5))
    stable_near = Outcome(r, stable=[True, True], felt=_felt(0.9))
    assert choose_variant([unstable_but_close, stable_far, stable_near]) == 2
    assert choose_variant([unstable_but_close, Outcome(r, [False, False], felt=_felt(1.0))]) == 0
    with pytest.raises(ValueError):
        choose_variant([])


def test_the_summary_separates_the_design_model_from_the_unseen_objects() -> None:
    def cond(obj: str, lp: dict[str, Any], peer: dict[str, Any]) -> dict[str, Any]:
        c: dict[str, Any] = {
            "object": obj, "k_o_n_per_m": 300.0, "sim_rate_hz": 20.0, "delay_ms": 0.0,
            "schemes": {},
        }  # fmt: skip
        for s, r in (("local-p", lp), ("mmt", peer)):
            c["schemes"][s] = {
                **r, "variant": "", "outside_stable": "", "felt": {},
                "hold_p2p_mm_max": 0.0, "peak_penetration_impact_mm_max": 1.0,
                "energy_out_mj_max": 0.0, "force_ripple_n_max": 0.0,
            }  # fmt: skip
        rank(c)
        return c

    conds = [
        cond("spring", _rec(True, 0.0), _rec(True, 0.0)),
        cond("sls", _rec(False, 0.0, "10"), _rec(True, 0.05)),
        cond("stiffening", _rec(True, 0.5), _rec(True, 0.05)),
    ]
    s = summarize(conds, ["local-p", "mmt"])
    assert s["local-p"]["box_stable_fraction_unseen"] == 0.5
    assert s["local-p"]["near_best_fraction_box_spring"] == 1.0
    assert s["local-p"]["near_best_fraction_box_unseen"] == 0.0
    assert s["mmt"]["near_best_fraction_box_unseen"] == 1.0
    prod = s["product"]
    assert prod["box_stable_fraction_unseen"] == 0.5
    assert [p["object"] for p in prod["peer_better"]] == ["sls", "stiffening"]
    assert s["by_object"]["sls"]["local-p"]["box_stable_fraction"] == 0.0
