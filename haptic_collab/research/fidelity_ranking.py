"""How ``haptic bench fidelity`` judges the schemes: the felt error, the tuning that represents a
peer, the ranking of one condition and the summary over the grid.

A condition's records are what :mod:`haptic_collab.bench.fidelity` collects per scheme
(:class:`Outcome`, :func:`scheme_record`); with every hand of the box in the loop, a scheme
counts in a condition only if it is stable with every hand on every trajectory; its felt error
is the largest ``|ln |q(f)||`` over :data:`BAND_HZ`, ``q`` the felt dynamic stiffness over the
object's own (:func:`haptic_collab.research.fidelity_metrics.felt_response`); the best is the
smallest, and every scheme within the stiffness JND of it (:data:`STIFFNESS_JND`) is tied with
it (:func:`rank`). :func:`summarize` sums the ranked conditions up.
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from haptic_collab.research.fidelity_schemes import LOCAL_MODELS, Rendering

#: Frequencies [Hz] of the felt impedance (0.5-30 Hz, docs/fidelity.md).
FELT_HZ = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 30.0)
#: The frequencies the ranking judges the felt stiffness over: the band of voluntary hand motion
#: in which people judge stiffness by pressing (Brooks 1990: up to 5-10 Hz); above it the
#: impedance is reported, not ranked.
BAND_HZ = (0.5, 1.0, 2.0, 4.0, 8.0)

#: Relative difference in felt stiffness below which a user cannot tell two renderings apart:
#: 10 %, under the Weber fractions measured for stiffness and compliance (15 % in Bergmann Tiest
#: and Kappers 2009, "Cues for haptic perception of compliance"; 23 % in Jones and Hunter 1990,
#: "A perceptual analysis of stiffness"), so the judgement errs against whoever is not the best.
STIFFNESS_JND = 0.10

Felt = dict[float, "tuple[float, float] | None"]


def felt_error(felt: Felt) -> float:
    """The largest ``|ln |q(f)||`` over :data:`BAND_HZ` (0: the object's own stiffness at every
    frequency of the band); ``inf`` when any of them could not be measured (a limit cycle, an
    unsettled or runaway response)."""
    worst = 0.0
    for hz in BAND_HZ:
        q = felt.get(hz)
        if q is None or not (q[0] > 0.0 and math.isfinite(q[0])):
            return math.inf
        worst = max(worst, abs(math.log(q[0])))
    return worst


@dataclass
class Outcome:
    """One rendering (a scheme's tuning) in one condition.

    ``stable`` holds one flag per (trajectory, box hand), in the grid's order; ``outside`` one
    per (trajectory, outside hand). ``metrics`` are the box cells' :class:`CellMetrics` JSON.
    ``follow_error`` is set in the two-user grid (:func:`follow_error`): it is then the error the
    outcome is ranked by, in place of the felt error.
    """

    rendering: Rendering
    stable: list[bool] = field(default_factory=list)
    outside: list[bool] = field(default_factory=list)
    metrics: list[dict[str, Any]] = field(default_factory=list)
    impact: list[dict[str, Any]] = field(default_factory=list)
    felt: Felt = field(default_factory=dict)
    follow_error: float | None = None

    @property
    def error(self) -> float:
        """The error it is ranked by: :attr:`follow_error` in the two-user grid, else the
        :func:`felt_error` of its felt response."""
        if self.follow_error is not None:
            return self.follow_error
        return felt_error(self.felt)

    @property
    def box_stable(self) -> bool:
        """Stable with every hand of the box on every trajectory."""
        return bool(self.stable) and all(self.stable)


def choose_variant(outcomes: Sequence[Outcome]) -> int:
    """Index of a peer's tuning that represents it in a condition: stable with every hand of the
    box if any is, then the most hands stable, then the smallest :func:`felt_error`."""
    if not outcomes:
        raise ValueError("choose_variant needs at least one outcome")
    return min(
        range(len(outcomes)),
        key=lambda i: (
            not outcomes[i].box_stable,
            -sum(outcomes[i].stable),
            outcomes[i].error,
        ),
    )


def scheme_record(o: Outcome) -> dict[str, Any]:
    err = o.error
    return {
        "variant": o.rendering.variant,
        "box_stable": o.box_stable,
        "stable_cells": "".join("1" if s else "0" for s in o.stable),
        "outside_stable": "".join("1" if s else "0" for s in o.outside),
        "felt": {f"{hz:g}": (None if q is None else [q[0], q[1]]) for hz, q in o.felt.items()},
        "felt_error": None if math.isinf(err) else err,
        "hold_p2p_mm_max": max((m["hold_p2p_mm"] for m in o.metrics), default=None),
        "peak_penetration_impact_mm_max": max(
            (m["peak_penetration_mm"] for m in o.impact), default=None
        ),
        "energy_out_mj_max": max((m["energy_out_mj"] for m in o.metrics), default=None),
        "force_ripple_n_max": max((m["force_ripple_n"] for m in o.metrics), default=None),
    }


def follow_error(
    before_n: float, during_n: float, after_n: float, object_rise_n: float, ripple_n: float
) -> float:
    """How far a user held still feels another user's press from what the object does
    (the two-user grid): the largest ``|ln|`` of the force's rise while the other holds
    (``during_n - before_n`` [N]) and of its fall once the other let go (``during_n - after_n``)
    over the object's own rise ``object_rise_n`` [N] (> 0); ``inf`` where the felt rise or fall
    is not positive or the force is not still while held (``ripple_n`` [N], its peak to peak in
    the held window, more than 10 % of the object's rise: a ringing, not a press felt)."""
    rise, fall = during_n - before_n, during_n - after_n
    if not (object_rise_n > 0.0 and rise > 0.0 and fall > 0.0):
        return math.inf
    if not (math.isfinite(ripple_n) and ripple_n <= 0.1 * object_rise_n):
        return math.inf
    return max(abs(math.log(rise / object_rise_n)), abs(math.log(fall / object_rise_n)))


def _ties(errors: dict[str, float]) -> tuple[list[str], list[str]]:
    """(best, within the JND of the best) among schemes with a finite felt error."""
    finite = {s: e for s, e in errors.items() if math.isfinite(e)}
    if not finite:
        return [], []
    best = min(finite.values())
    top = [s for s, e in finite.items() if e <= best + 1e-9]
    near = [s for s, e in finite.items() if e <= best + math.log1p(STIFFNESS_JND) + 1e-12]
    return top, near


def rank(condition: dict[str, Any]) -> None:
    """Rank one condition's schemes in place (module docstring): ``best`` and ``near_best``
    with every hand of the box, and ``per_hand`` (counts over its (trajectory, hand) cells of
    each scheme best / within the JND of the best among those stable with that hand)."""
    recs = condition["schemes"]
    errors = {
        s: (r["felt_error"] if r["felt_error"] is not None else math.inf) for s, r in recs.items()
    }
    box = {s: e for s, e in errors.items() if recs[s]["box_stable"]}
    condition["best"], condition["near_best"] = _ties(box)
    n_cells = max((len(r["stable_cells"]) for r in recs.values()), default=0)
    best_n: dict[str, int] = dict.fromkeys(recs, 0)
    near_n: dict[str, int] = dict.fromkeys(recs, 0)
    for k in range(n_cells):
        ok = {s: e for s, e in errors.items() if recs[s]["stable_cells"][k : k + 1] == "1"}
        top, near = _ties(ok)
        for s in top:
            best_n[s] += 1
        for s in near:
            near_n[s] += 1
    condition["per_hand"] = {"cells": n_cells, "best": best_n, "near_best": near_n}


def _frac(n: int, d: int) -> float | None:
    return n / d if d else None


def summarize(conditions: list[dict[str, Any]], schemes: Sequence[str]) -> dict[str, Any]:
    """The summary of ranked conditions (:func:`rank`).

    Per scheme: ``box_stable_fraction`` (conditions in which it is stable with every hand of the
    box), ``best_fraction_box`` and ``near_best_fraction_box`` (best / within the JND of the
    best with every hand of the box), the same on the design model (``_spring``) and on the
    objects the design did not see (``_unseen``), the per-hand shares (``per_hand_*``),
    ``outside_stable_fraction`` (cells with hands outside the box), the medians of ``|q|`` and
    of its phase [rad] at each felt frequency over the conditions where it is box-stable, the
    largest energy it gave a user [mJ], the median peak penetration on impact [mm], and which
    tunings represented it. ``by_object``: each object's box-stable and near-best shares per
    scheme. ``product``: the local models' shares (either of them), and ``peer_better``: the
    conditions where a peer is better than both local models by more than the JND.
    """
    unseen = [c for c in conditions if c["object"] != "spring"]
    spring = [c for c in conditions if c["object"] == "spring"]
    out: dict[str, Any] = {}
    for s in schemes:
        mine = [c for c in conditions if s in c["schemes"]]
        if not mine:
            continue
        recs = [c["schemes"][s] for c in mine]
        stable_recs = [r for r in recs if r["box_stable"]]
        cells = sum(len(r["stable_cells"]) for r in recs)
        outside = "".join(r["outside_stable"] for r in recs)
        mags: dict[str, float | None] = {}
        phases: dict[str, float | None] = {}
        for hz in FELT_HZ:
            key = f"{hz:g}"
            vals = [r["felt"][key] for r in stable_recs if r["felt"].get(key) is not None]
            mags[key] = statistics.median(v[0] for v in vals) if vals else None
            phases[key] = statistics.median(v[1] for v in vals) if vals else None
        errs = [r["felt_error"] for r in stable_recs if r["felt_error"] is not None]
        variants: dict[str, int] = defaultdict(int)
        for r in recs:
            variants[r["variant"] or "-"] += 1
        pen = [
            r["peak_penetration_impact_mm_max"]
            for r in stable_recs
            if r["peak_penetration_impact_mm_max"] is not None
        ]
        row = {
            "conditions": len(mine),
            "box_stable_fraction": sum(r["box_stable"] for r in recs) / len(recs),
            "best_fraction_box": sum(s in c["best"] for c in mine) / len(mine),
            "near_best_fraction_box": sum(s in c["near_best"] for c in mine) / len(mine),
            "per_hand_stable_fraction": _frac(
                sum(r["stable_cells"].count("1") for r in recs), cells
            ),
            "per_hand_best_fraction": _frac(sum(c["per_hand"]["best"][s] for c in mine), cells),
            "per_hand_near_best_fraction": _frac(
                sum(c["per_hand"]["near_best"][s] for c in mine), cells
            ),
            "outside_stable_fraction": _frac(outside.count("1"), len(outside)),
            "median_felt_ratio": mags,
            "median_felt_phase_rad": phases,
            "median_felt_error": statistics.median(errs) if errs else None,
            "max_energy_out_mj": max(
                (r["energy_out_mj_max"] for r in stable_recs if r["energy_out_mj_max"] is not None),
                default=None,
            ),
            "median_peak_penetration_impact_mm": statistics.median(pen) if pen else None,
            "variants": dict(variants),
        }
        for tag, group in (("spring", spring), ("unseen", unseen)):
            g = [c for c in group if s in c["schemes"]]
            row[f"box_stable_fraction_{tag}"] = _frac(
                sum(c["schemes"][s]["box_stable"] for c in g), len(g)
            )
            row[f"near_best_fraction_box_{tag}"] = _frac(
                sum(s in c["near_best"] for c in g), len(g)
            )
        out[s] = row
    by_object: dict[str, dict[str, Any]] = {}
    for name in dict.fromkeys(c["object"] for c in conditions):
        g = [c for c in conditions if c["object"] == name]
        by_object[name] = {
            s: {
                "box_stable_fraction": sum(c["schemes"][s]["box_stable"] for c in g) / len(g),
                "near_best_fraction_box": sum(s in c["near_best"] for c in g) / len(g),
            }
            for s in schemes
            if all(s in c["schemes"] for c in g)
        }
    ours = [s for s in schemes if s in LOCAL_MODELS]
    peer_better = []
    for c in conditions:
        if not ours or any(s in c["near_best"] for s in ours) or not c["best"]:
            continue
        lm_errs = {s: c["schemes"][s]["felt_error"] for s in ours}
        peer_better.append(
            {
                "object": c["object"],
                "k_o_n_per_m": c["k_o_n_per_m"],
                "sim_rate_hz": c["sim_rate_hz"],
                "delay_ms": c["delay_ms"],
                "best": c["best"],
                "best_felt_error": c["schemes"][c["best"][0]]["felt_error"],
                "local_model_felt_error": lm_errs,
                "local_model_box_stable": {s: c["schemes"][s]["box_stable"] for s in ours},
            }
        )

    def share(group: list[dict[str, Any]], key: str) -> float | None:
        if not ours:
            return None
        if key == "box_stable":
            return _frac(
                sum(all(c["schemes"][s]["box_stable"] for s in ours) for c in group), len(group)
            )
        return _frac(sum(any(s in c[key] for s in ours) for c in group), len(group))

    out["by_object"] = by_object
    out["product"] = {
        "local_models": ours,
        "box_stable_fraction": share(conditions, "box_stable"),
        "box_stable_fraction_unseen": share(unseen, "box_stable"),
        "near_best_fraction_box": share(conditions, "near_best"),
        "near_best_fraction_box_spring": share(spring, "near_best"),
        "near_best_fraction_box_unseen": share(unseen, "near_best"),
        "best_fraction_box": share(conditions, "best"),
        "peer_better": peer_better,
    }
    out["stiffness_jnd"] = STIFFNESS_JND
    out["band_hz"] = list(BAND_HZ)
    out["conditions"] = len(conditions)
    return out
