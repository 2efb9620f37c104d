"""``haptic bench drawn``: the product on conditions drawn at random from the declared set.

Each run draws ``n`` conditions (:func:`shared.declared_set.draw_conditions`) with a seed it
prints (a new seed each run unless one is given), and runs each with several hands of the box
(:func:`shared.declared_set.draw_hand`, the box's least damped, stiffest corner always among
them), both sampling phases and both local models, through the product's own client
(:mod:`haptic_collab.research.drawn_loop`). A condition is *box-stable* for a local model when
every one of its runs is stable. The summary gives the share of box-stable conditions, for one
user and for several, per local model, and the conditions that were not.

This module reads a clock only to report wall time.
"""

from __future__ import annotations

import os
import secrets
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from typing import Any, Literal

import numpy as np

from haptic_collab.research.drawn_loop import run
from haptic_collab.shared.declared_set import DrawnCondition, DrawnHand, draw_conditions, draw_hand

#: The box's least damped, heaviest, stiffest hand: always among a condition's hands.
WORST_HAND = DrawnHand(0.6, 2.0, 1000.0)
#: Sampling phases run (fractions of a simulation period): the server's tick just after a state
#: and just before the next.
PHASES = (0.05, 0.45)


def _job(args: tuple[DrawnCondition, DrawnHand, str, float, str]) -> dict[str, Any]:
    cond, hand, mode, phase, passivity = args
    r = run(cond, hand, mode=mode, phase=phase, passivity=passivity)  # type: ignore[arg-type]
    return {
        "index": cond.index,
        "hand": asdict(hand),
        "mode": mode,
        "phase": phase,
        "stable": r.stable,
        "hold_p2p_mm": r.hold_p2p_mm,
        "force_hold_n": r.force_hold_n,
        "sources": r.sources,
        "passivity_dissipated_mj": r.passivity_dissipated_mj,
    }


def run_drawn(
    seed: int | None = None,
    n: int = 24,
    *,
    hands: int = 3,
    modes: Sequence[Literal["p", "pi"]] = ("p", "pi"),
    passivity: Literal["auto", "on", "off"] = "auto",
    workers: int | None = None,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Draw, run and summarise (module docstring). ``seed`` None: a fresh one; ``log`` gets a
    line per tenth of the runs done."""
    seed = secrets.randbits(32) if seed is None else int(seed)
    t0 = time.perf_counter()
    conds = draw_conditions(seed, n)
    rng = np.random.default_rng([seed, 1])
    jobs = []
    for c in conds:
        hs = [WORST_HAND] + [draw_hand(rng) for _ in range(max(0, hands - 1))]
        for h in hs:
            for mode in modes:
                for ph in PHASES:
                    jobs.append((c, h, mode, ph, passivity))
    # long conditions first (fast rates, several users) so the pool ends together
    order = sorted(range(len(jobs)), key=lambda i: -(jobs[i][0].sim_rate_hz * jobs[i][0].users))
    workers = workers or max(1, min(2, os.cpu_count() or 1))
    results: list[dict[str, Any]] = [{}] * len(jobs)
    if log is not None:
        log(f"drawn: seed {seed}, {n} conditions, {len(jobs)} runs on {workers} processes")
    with ProcessPoolExecutor(workers) as ex:
        done = 0
        for i, res in zip(order, ex.map(_job, [jobs[i] for i in order], chunksize=1), strict=True):
            results[i] = res
            done += 1
            if log is not None and done % max(1, len(jobs) // 10) == 0:
                log(f"drawn: {done} of {len(jobs)} runs ({time.perf_counter() - t0:.0f} s)")
    per: dict[tuple[int, str], list[dict[str, Any]]] = {}
    for r in results:
        per.setdefault((r["index"], r["mode"]), []).append(r)
    conditions = []
    for c in conds:
        row: dict[str, Any] = {"condition": _cond_json(c)}
        for mode in modes:
            runs = per[(c.index, mode)]
            row[mode] = {
                "box_stable": all(r["stable"] for r in runs),
                "worst_hold_p2p_mm": max(r["hold_p2p_mm"] for r in runs),
                "runs": runs,
            }
        conditions.append(row)
    summary: dict[str, Any] = {}
    for mode in modes:
        for label, sel in (
            ("one_user", lambda c: c.users == 1),
            ("several_users", lambda c: c.users > 1),
        ):
            rows = [r for r, c in zip(conditions, conds, strict=True) if sel(c)]
            ok = sum(r[mode]["box_stable"] for r in rows)
            summary[f"{mode}_{label}"] = {
                "box_stable": ok,
                "of": len(rows),
                "share": (ok / len(rows)) if rows else None,
                "not_stable": [r["condition"]["index"] for r in rows if not r[mode]["box_stable"]],
            }
    return {
        "seed": seed,
        "n": n,
        "hands": hands,
        "phases": list(PHASES),
        "passivity": passivity,
        "wall_s": time.perf_counter() - t0,
        "summary": summary,
        "conditions": conditions,
    }


def _cond_json(c: DrawnCondition) -> dict[str, Any]:
    d = asdict(c)
    return d
