"""Reproduce Fig. 10 and 11 of Barbagli, Prattichizzo & Salisbury (IJRR 2005) on the 3-D balloon.

Section 7 of the paper: a proportional local model on a Phantom Desktop touching a triangle-mesh
deformable object with K_o = 1.0 N/mm at the contact. K_h = 0.6 and 0.7 N/mm (Fig. 10) are
stable; K_h = 1.2 N/mm (Fig. 11) violates eq. (8) and is unstable.

This module owns the figures: which cases each runs, the re-run at the full loop's worst
sampling tick, the notes comparing our verdicts with the paper's, and the JSON and PNG files.
Each case is one press of the stiffened balloon through the product's own World, simulated hand
and servo, run in-process (:func:`haptic_collab.research.press_3d.run_case` on the harness of
:mod:`haptic_collab.research.harness_3d`), and judged three ways
(:func:`haptic_collab.research.press_3d.case_result`): the simulation loop (eq. 8 for P, eq. 15
for PI; the probe as a position source), the full loop with the hand
(:func:`shared.full_loop.analyze_full_loop`, DESIGN section 6b), and the time response: the
peak-to-peak probe depth over the last second of the hold (below 0.5 mm the product calls the
hold stable). The drawings are :mod:`haptic_collab.research.plots_3d`.

Usage::

    from pathlib import Path
    from haptic_collab.research.reproduce_3d import reproduce_3d
    results = reproduce_3d("all", Path("figs"))   # figs/fig10.json, fig10.png, fig11.json, ...
"""

from __future__ import annotations

import pathlib
from collections.abc import Sequence
from typing import Any, Literal

from haptic_collab.client.devices.profiles import get_sim_profile
from haptic_collab.client.devices.sim import HandParams
from haptic_collab.research.harness_3d import PROFILE, SERVO_RATE_HZ, SIM_RATE_HZ, combined_hand
from haptic_collab.research.plots_3d import plot_fig10, plot_fig11
from haptic_collab.research.press_3d import (
    PAPER_CASES,
    PROBE_DEPTH_M,
    STABLE_HOLD_P2P_MM,
    THETA_M,
    Case3D,
    CaseRun,
    StiffBalloon,
    Timeline3D,
    case_result,
    hand_json,
    product_cases,
    run_case,
    stiff_balloon,
)

__all__ = ["Figure3D", "fig10", "fig11", "reproduce_3d"]

Figure3D = Literal["fig10", "fig11", "all"]

# --------------------------------------------------------------------------------------------
# notes
# --------------------------------------------------------------------------------------------


def _tick_ranges(ticks: Sequence[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"``."""
    out: list[str] = []
    for j in ticks:
        if out and out[-1].split("-")[-1] == str(j - 1):
            out[-1] = f"{out[-1].split('-')[0]}-{j}"
        else:
            out.append(str(j))
    return ", ".join(out)


def _paper_note(
    cases: dict[str, dict[str, Any]],
    hand: HandParams,
    phase_check: dict[str, dict[str, Any]] | None = None,
) -> str:
    """Where our verdicts disagree with the paper's experiment, written from the measured numbers."""
    felt = combined_hand(hand)
    paper = [(name, c) for name, c in cases.items() if c.get("paper_stable") is not None]
    if not paper:
        return ""

    def kh(c: dict[str, Any]) -> str:
        return f"K_h = {c['k_h_n_per_m']:g}"

    def agreement(key: str) -> str:
        bad = [kh(c) for _, c in paper if c[key] != c["paper_stable"]]
        return (
            "agrees with the paper" if not bad else f"DISAGREES with the paper for {', '.join(bad)}"
        )

    j = paper[0][1]["sample_tick"]
    parts = [
        "Paper (Phantom Desktop, K_o = 1.0 N/mm): K_h = 0.6 and 0.7 N/mm stable, 1.2 N/mm unstable.",
        f"Simulation loop (eq. 8, probe as a position source): {agreement('sim_loop_stable')}.",
        f"Time runs (the world takes the force of servo tick {j} of each period, the paper's "
        "decimator), hold p2p over the last second: "
        + ", ".join(
            f"{kh(c)}: {c['hold_p2p_mm']:.2f} mm (full-loop rho "
            f"{c['full_loop_spectral_radius_at_sample_tick']:.2f} at that tick)"
            for _, c in paper
        )
        + f"; {agreement('hold_stable')}.",
        f"Full loop with our default simulated hand ({felt.mass_kg:g} kg, "
        f"{felt.damping_n_s_per_m:g} N*s/m, {felt.stiffness_n_per_m:g} N/m as the probe feels "
        "it), worst sampling tick (the product's criterion): "
        + ", ".join(
            f"{kh(c)}: {'stable' if c['full_loop_stable'] else 'unstable'} "
            f"(rho {c['full_loop_spectral_radius']:.3f}"
            + (
                f", unstable for ticks {_tick_ranges(c['full_loop_unstable_sample_ticks'])})"
                if c["full_loop_unstable_sample_ticks"]
                else ")"
            )
            for _, c in paper
        )
        + f"; {agreement('full_loop_stable')}.",
    ]
    if phase_check:
        parts.append(
            "Run again with the world taking the force of the worst tick: "
            + ", ".join(
                f"K_h = {p['k_h_n_per_m']:g} at tick {p['sample_tick']}: hold p2p "
                f"{p['hold_p2p_mm']:.2f} mm ({'stable' if p['hold_stable'] else 'oscillates'})"
                for p in phase_check.values()
            )
            + "."
        )
    if any(c["full_loop_stable"] != c["paper_stable"] for _, c in paper):
        parts.append(
            "The paper's analysis holds the probe as a position source; a hand holding the device "
            "closes a second loop through the local model that the 20 Hz proxy jumps excite "
            "(DESIGN section 6b), and which sampling tick the simulation sees decides whether it "
            "grows. The paper's real hand, Phantom and timing are not ours; nothing was tuned to "
            "match."
        )
    return " ".join(parts)


# --------------------------------------------------------------------------------------------
# figures
# --------------------------------------------------------------------------------------------


def _common(stiff: StiffBalloon, tl: Timeline3D, hand: HandParams) -> dict[str, Any]:
    return {
        "object": {
            "mesh": "default water balloon (server.objects.balloon, icosphere r = 0.1 m)",
            "n_vertices": stiff.n_vertices,
            "stiffness_scale": stiff.scale,
            "k_o_unscaled_top_n_per_m": stiff.k_o_unscaled,
            "k_o_top_n_per_m": stiff.k_o,
        },
        "servo_rate_hz": SERVO_RATE_HZ,
        "sim_rate_hz": SIM_RATE_HZ,
        "delay_ticks": 0,
        "device_profile": PROFILE,
        "hand": hand_json(hand),
        "timeline_s": {
            "approach": tl.approach_s,
            "press": tl.press_s,
            "hold": tl.hold_s,
            "hold_start": tl.hold_start_s,
            "end": tl.run_s,
            "standoff_m": tl.standoff_m,
        },
        "target_probe_depth_m": PROBE_DEPTH_M,
        "stable_hold_p2p_mm": STABLE_HOLD_P2P_MM,
    }


def _paper_case(name: str) -> Case3D:
    for n, k_h, stable in PAPER_CASES:
        if n == name:
            return Case3D(name=n, source="paper", mode="p", k_h=k_h, paper_stable=stable)
    raise KeyError(name)


def _cap_note() -> str:
    cap = get_sim_profile(PROFILE).limits.max_stiffness_n_per_m
    return (
        f"The {PROFILE} profile limits K_h to {cap:g} N/m; for the paper's gains above it the "
        "limit is raised to the gain (the paper ran 1.2 N/mm on its Phantom)."
    )


def _run_all(
    stiff: StiffBalloon,
    cases: Sequence[Case3D],
    tl: Timeline3D,
    hand: HandParams,
    sample_tick: int,
) -> tuple[list[CaseRun], dict[str, dict[str, Any]]]:
    runs = [run_case(stiff, c, tl, hand, sample_tick) for c in cases]
    results = {r.case.name: case_result(r, tl, hand, stiff.k_o) for r in runs}
    return runs, results


def _phase_check(
    stiff: StiffBalloon,
    runs: Sequence[CaseRun],
    results: dict[str, dict[str, Any]],
    tl: Timeline3D,
    hand: HandParams,
) -> tuple[dict[str, CaseRun], dict[str, dict[str, Any]]]:
    """Re-run each paper case whose full loop is unstable at the worst tick, at that tick."""
    worst_runs: dict[str, CaseRun] = {}
    check: dict[str, dict[str, Any]] = {}
    for run in runs:
        res = results[run.case.name]
        j = res["full_loop_worst_sample_tick"]
        if run.case.source != "paper" or res["full_loop_stable"] or j == run.sample_tick:
            continue
        again = run_case(stiff, run.case, tl, hand, sample_tick=j)
        r2 = case_result(again, tl, hand, stiff.k_o)
        worst_runs[run.case.name] = again
        check[run.case.name] = {
            "k_h_n_per_m": r2["k_h_n_per_m"],
            "sample_tick": j,
            "full_loop_spectral_radius_at_sample_tick": r2[
                "full_loop_spectral_radius_at_sample_tick"
            ],
            "hold_p2p_mm": r2["hold_p2p_mm"],
            "hold_stable": r2["hold_stable"],
            "steady_state_error_mm": r2["steady_state_error_mm"],
        }
    return worst_runs, check


def fig10(
    out_dir: pathlib.Path,
    *,
    stiff: StiffBalloon | None = None,
    timeline: Timeline3D | None = None,
    hand: HandParams | None = None,
    product: bool = True,
    sample_tick: int = 0,
) -> dict[str, Any]:
    """Fig. 10: K_h = 600 and 700 N/m (P) on K_o = 1000 N/m, plus the product's own gains.

    Writes ``fig10.png`` into ``out_dir`` and returns the JSON object: per case (``cases``) the
    figures of merit of :func:`case_result`; ``worst_phase`` the paper cases re-run with the world
    taking the force of the full loop's worst sampling tick; ``note`` where our verdicts disagree
    with the paper's; ``notes`` the rest (the device's stiffness limit, product cases skipped).
    """
    tl = timeline if timeline is not None else Timeline3D()
    hand = hand if hand is not None else HandParams()
    stiff = stiff if stiff is not None else stiff_balloon()
    cases = [_paper_case("kh600"), _paper_case("kh700")]
    notes: list[str] = []
    if product:
        extra, notes = product_cases(stiff.k_o)
        cases += extra
    runs, results = _run_all(stiff, cases, tl, hand, sample_tick)
    worst_runs, check = _phase_check(stiff, runs, results, tl, hand)
    plot_fig10(out_dir / "fig10.png", runs, results, tl, worst_runs)
    out = _common(stiff, tl, hand)
    out["cases"] = results
    out["worst_phase"] = check
    out["note"] = _paper_note(results, hand, check)
    out["notes"] = [_cap_note(), *notes]
    if any(c.source == "product" for c in cases):
        out["notes"].append(
            "The product's gains run on the same servo as the paper's (fixed theta = "
            f"{THETA_M * 1000.0:g} mm, no passivity layer), not with every client.app setting."
        )
    return out


def fig11(
    out_dir: pathlib.Path,
    *,
    stiff: StiffBalloon | None = None,
    timeline: Timeline3D | None = None,
    hand: HandParams | None = None,
    sample_tick: int = 0,
) -> dict[str, Any]:
    """Fig. 11: K_h = 1200 N/m (P) on K_o = 1000 N/m violates eq. 8.

    Writes ``fig11.png`` (consecutive world ticks of the surface and the depth trace) and returns
    the JSON object, as :func:`fig10`.
    """
    tl = timeline if timeline is not None else Timeline3D()
    hand = hand if hand is not None else HandParams()
    stiff = stiff if stiff is not None else stiff_balloon()
    runs, results = _run_all(stiff, [_paper_case("kh1200")], tl, hand, sample_tick)
    frames = plot_fig11(out_dir / "fig11.png", runs[0], results["kh1200"], tl)
    out = _common(stiff, tl, hand)
    out["cases"] = results
    out["frames_t_s"] = frames
    out["note"] = _paper_note(results, hand)
    out["notes"] = [_cap_note()]
    return out


def reproduce_3d(
    figure: Figure3D,
    out_dir: pathlib.Path,
    *,
    timeline: Timeline3D | None = None,
    hand: HandParams | None = None,
    product: bool = True,
    sample_tick: int = 0,
) -> dict[str, dict[str, Any]]:
    """Recompute the paper's Fig. 10 and/or 11 and write ``<fig>.json`` and ``<fig>.png``.

    Parameters
    ----------
    figure : {"fig10", "fig11", "all"}
    out_dir : pathlib.Path
        Output directory, created if missing.
    timeline : Timeline3D, optional
        The press (default: 0.3 s approach, 0.7 s press, 2.5 s hold).
    hand : HandParams, optional
        The simulated hand (default :class:`HandParams`).
    product : bool
        Also run the product's own gains (Fig. 10), when ``shared.gains.design`` exists.
    sample_tick : int
        Servo tick of each period whose force the world takes (default 0, the paper's
        decimator; see :func:`run_case`).

    Returns
    -------
    dict
        The JSON objects written, keyed by figure name. With both figures, each ``note``
        covers all three of the paper's gains.

    Raises
    ------
    ValueError
        Unknown figure name.
    """
    import json

    if figure not in ("fig10", "fig11", "all"):
        raise ValueError(f"figure must be one of fig10, fig11, all; got {figure!r}")
    hand = hand if hand is not None else HandParams()
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stiff = stiff_balloon()
    results: dict[str, dict[str, Any]] = {}
    if figure in ("fig10", "all"):
        results["fig10"] = fig10(
            out_dir,
            stiff=stiff,
            timeline=timeline,
            hand=hand,
            product=product,
            sample_tick=sample_tick,
        )
    if figure in ("fig11", "all"):
        results["fig11"] = fig11(
            out_dir, stiff=stiff, timeline=timeline, hand=hand, sample_tick=sample_tick
        )
    if len(results) == 2:  # one note over the paper's three gains
        note = _paper_note(
            {**results["fig10"]["cases"], **results["fig11"]["cases"]},
            hand,
            results["fig10"]["worst_phase"],
        )
        for data in results.values():
            data["note"] = note
    for name, data in results.items():
        with open(out_dir / f"{name}.json", "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=2, allow_nan=False)
            fh.write("\n")
    return results
