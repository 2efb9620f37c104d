"""The design subcommands: ``haptic stability``, ``haptic gains`` and ``haptic gains-table``.

They judge and design the local model (shared.stability, shared.full_loop, shared.gains.design):
each command's handler (``_cmd_*``) and its parser (``_add_*``). Their implementation is imported
when the command runs, not when the parser is built.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from haptic_collab.cli.args import (
    CliError,
    _add_shared,
    _nonneg,
    _nonneg_int,
    _positive,
    _whole_positive,
    _why,
)
from haptic_collab.shared.felt_stiffness import object_stiffness


# ---------------------------------------------------------------------------------------- stability
def _hand_from(args: argparse.Namespace) -> object | None:
    """The Hand of --hand-mass/--hand-damping/--hand-stiffness (all three or none)."""
    from haptic_collab.shared.full_loop import Hand

    vals = (args.hand_mass, args.hand_damping, args.hand_stiffness)
    if all(v is None for v in vals):
        return None
    if any(v is None for v in vals):
        raise CliError("give --hand-mass, --hand-damping and --hand-stiffness together")
    try:
        return Hand(args.hand_mass, args.hand_damping, args.hand_stiffness)
    except ValueError as exc:
        raise CliError(_why(exc)) from None


def _cmd_stability(args: argparse.Namespace) -> int:
    from haptic_collab.shared.full_loop import analyze_full_loop
    from haptic_collab.shared.stability import analyze

    hand = _hand_from(args)
    try:
        res = analyze(
            args.k_o,
            args.k_h,
            i_gain=args.i_gain,
            damping=args.damping,
            servo_rate_hz=args.servo_rate,
            sim_rate_hz=args.sim_rate,
            delay_ticks=args.delay_ticks,
            sample_tick=args.sample_tick,
        )
        full = (
            None
            if hand is None
            else analyze_full_loop(
                hand,  # type: ignore[arg-type]
                k_o=args.k_o,
                k_h=args.k_h,
                i_gain=args.i_gain,
                b_h=args.b_h,
                damping=args.damping,
                servo_rate_hz=args.servo_rate,
                sim_rate_hz=args.sim_rate,
                delay_ticks=args.delay_ticks,
                proxy_hold=args.proxy_hold,
                own_gain=args.own_gain,
            )
        )
    except ValueError as exc:
        raise CliError(_why(exc)) from None
    if args.json:
        out = res.to_json()
        out["full_loop"] = None if full is None else full.to_json()
        print(json.dumps(out))
        return 0
    kind = "proportional-integral" if args.i_gain > 0 else "proportional"
    verdict = "STABLE" if res.stable else "UNSTABLE"
    print(f"{verdict}: {kind} local model, K_h = {args.k_h:g} N/m on K_o = {args.k_o:g} N/m")
    print(
        f"  servo {args.servo_rate:g} Hz, simulation {args.sim_rate:g} Hz (N = {res.rate_ratio}), "
        f"B_o = {res.b_o:g} N/m, I*N*T = {res.nti:g} N/m, delay {args.delay_ticks} tick(s)"
    )
    print(f"  spectral radius {res.spectral_radius:.4f} (stable below 1)")
    if res.analytic_stable is not None:
        agree = "agrees" if res.analytic_stable == res.stable else "DISAGREES"
        print(f"  {res.condition}: {'holds' if res.analytic_stable else 'fails'} ({agree})")
    else:
        print(f"  {res.condition}")
    if full is not None:
        fv = "STABLE" if full.stable else "UNSTABLE"
        print(
            f"  full loop with the hand ({args.hand_mass:g} kg, {args.hand_damping:g} N*s/m, "
            f"{args.hand_stiffness:g} N/m): {fv}, spectral radius {full.spectral_radius:.4f} "
            f"(worst sampling tick {full.worst_sample_tick})"
        )
    return 0


def _add_stability(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "stability",
        help="stability of the simulation loop for given K_o, K_h, I (paper eq. 8, 10, 15, 16)",
        description="Verdict on the slow-rate simulation loop z^-(1+D) L_h(z) D(z) (Fig. 6).",
    )
    _add_shared(p, "--k-o")
    p.add_argument("--k-h", type=_positive, required=True, help="local model stiffness K_h [N/m]")
    p.add_argument(
        "--i-gain",
        type=_nonneg,
        default=0.0,
        help="integral weight I [N/(m*s)]; 0 = P (default %(default)s)",
    )
    p.add_argument(
        "--damping",
        type=_nonneg,
        default=0.0,
        help="object damping b [N*s/m] (default %(default)s)",
    )
    _add_shared(p, "--servo-rate", help="servo rate 1/T [Hz] (default %(default)s)")
    _add_shared(p, "--sim-rate", help="simulation rate [Hz] (default %(default)s)")
    _add_shared(p, "--delay-ticks")
    p.add_argument(
        "--sample-tick",
        type=_nonneg_int,
        default=0,
        help="servo tick of the period whose force the simulation samples (0: the paper's "
        "decimator) (default %(default)s)",
    )
    hand = p.add_argument_group(
        "full loop",
        "the combined hand and device as the probe feels them; with all three, the JSON gains "
        '"full_loop": {"stable", "spectral_radius", "worst_sample_tick"} (worst over every '
        "sampling tick; null without them)",
    )
    hand.add_argument(
        "--hand-mass", type=_positive, default=None, help="moving mass m [kg] (default: none)"
    )
    hand.add_argument(
        "--hand-damping", type=_nonneg, default=None, help="damping b [N*s/m] (default: none)"
    )
    hand.add_argument(
        "--hand-stiffness", type=_nonneg, default=None, help="stiffness k [N/m] (default: none)"
    )
    hand.add_argument(
        "--b-h", type=_nonneg, default=0.0, help="probe damper B_h [N*s/m] (default %(default)s)"
    )
    hand.add_argument(
        "--proxy-hold",
        choices=["zoh", "foh"],
        default="zoh",
        help="proxy hold (default %(default)s)",
    )
    hand.add_argument(
        "--own-gain",
        type=_nonneg,
        default=0.0,
        help="own-force compensation C_h [m/N] (docs/own-force.md; the paper's loop above is "
        "without it) (default %(default)s)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_stability)


# ------------------------------------------------------------------------------------------- gains
def _profile_design(
    profile: str, k_o: float, *, paper: bool, stiffer_by: float | None = None, **kw: Any
) -> Any:
    """The product's design (:func:`shared.gains.design.design_gains`, timed) for K_o with the
    stiffness and damping limits of the device profile ``profile``; ``paper``: without own-force
    compensation; ``stiffer_by`` (default the product's :data:`shared.gains.policy.STIFFER_BY`):
    checked up to ``(1 + stiffer_by) K_o``, or up to the one-tick stiffness ``K_o + B_o`` where
    that is higher (:func:`shared.gains.table.stiffest_k_o`, as a cell is checked). Raises KeyError
    (unknown profile) or ValueError (as the design)."""
    from haptic_collab.client.devices.profiles import get_sim_profile
    from haptic_collab.client.workers import timed
    from haptic_collab.shared.gains.design import design_gains
    from haptic_collab.shared.gains.policy import STIFFER_BY
    from haptic_collab.shared.gains.table import stiffest_k_o

    lim = get_sim_profile(profile).limits
    sb = STIFFER_BY if stiffer_by is None else float(stiffer_by)
    return timed(
        design_gains,
        k_o,
        k_h_max=lim.max_stiffness_n_per_m,
        b_h_max=lim.max_damping_n_s_per_m,
        own_force=not paper,
        k_o_hi=stiffest_k_o(k_o, sb, float(kw.get("b_o", 0.0))),
        stiffer_by=sb,
        **kw,
    )


def _cmd_gains(args: argparse.Namespace) -> int:
    try:
        d = _profile_design(
            args.profile,
            args.k_o,
            paper=args.paper,
            b_o=args.b_o,
            servo_rate_hz=args.servo_rate,
            sim_rate_hz=args.sim_rate,
            delay_ticks=args.delay_ticks,
            mode=args.local_model,
            margin=args.margin,
            stiffer_by=args.stiffer_by,
        )
    except (ValueError, KeyError) as exc:
        raise CliError(str(exc).strip("'\"")) from None
    out = d.to_json()
    if args.json:
        print(json.dumps(out))
        return 0
    kind = "PI" if d.i_gain > 0 else "P"
    print(
        f"{kind} local model for K_o = {args.k_o:g} N/m ({args.sim_rate:g} Hz, "
        f"{args.delay_ticks} tick(s) of delay, {args.profile}):"
    )
    print(
        f"  K_h = {d.k_h:.1f} N/m, I = {d.i_gain:.0f} N/(m*s), B_h = {d.b_h:.2f} N*s/m, "
        f"proxy {d.proxy_hold}"
    )
    if d.own_gain > 0.0:
        print(
            f"  own-force compensation C_h = {d.own_gain:.4g} m/N "
            f"(C_h K_h = {d.own_gain * d.k_h:.2f}; docs/own-force.md)"
        )
    felt = (
        f"  felt stiffness / K_o: {d.felt_stiffness_ratio_1hz:.3f} at 1 Hz, "
        f"{d.felt_stiffness_ratio_8hz:.3f} at 8 Hz"
    )
    if args.b_o > 0.0:
        # what a transparent rendering of the damped object is felt as (eq. 9; docs/gains.md)
        own = (
            abs(
                object_stiffness(
                    (1.0, 8.0), k_o=args.k_o, b_o=args.b_o, sim_period_s=1.0 / args.sim_rate
                )
            )[:, 0]
            / args.k_o
        )
        felt += f" (the object itself, eq. 9: {own[0]:.3f} and {own[1]:.3f})"
    print(felt)
    box = d.hand_box
    print(
        f"  worst spectral radius {d.worst_spectral_radius:.4f} over hands {box.mass_kg[0]:g}-"
        f"{box.mass_kg[1]:g} kg, {box.damping_n_s_per_m[0]:g}-{box.damping_n_s_per_m[1]:g} N*s/m, "
        f"{box.stiffness_n_per_m[0]:g}-{box.stiffness_n_per_m[1]:g} N/m, every sampling tick, "
        f"K_o' in [{d.k_o_range[0]:g}, {d.k_o_range[1]:g}] N/m ({d.design_ms:.0f} ms)"
    )
    return 0


def _add_gains(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "gains",
        help="the most transparent local model stable with the hand in the loop (full loop)",
        description="Design K_h, I, B_h and the proxy hold for an object stiffness: stable for "
        "every hand of the hand box, every force-sampling tick and K_o' from (1 - margin) K_o to "
        "(1 + stiffer-by) K_o, or to K_o + B_o where that is higher.",
    )
    _add_shared(p, "--k-o")
    _add_shared(
        p,
        "--local-model",
        help="local model: proportional or proportional-integral (default %(default)s)",
    )
    p.add_argument(
        "--b-o",
        type=_nonneg,
        default=0.0,
        help="object damping B_o [N/m] (eq. 9) (default %(default)s)",
    )
    _add_shared(p, "--sim-rate", help="simulation rate [Hz] (default %(default)s)")
    _add_shared(p, "--servo-rate", help="servo rate [Hz] (default %(default)s)")
    _add_shared(p, "--delay-ticks")
    _add_shared(
        p,
        "--profile",
        help="device profile whose limits bound K_h and B_h (phantom-desktop | touch) "
        "(default %(default)s)",
    )
    _add_shared(p, "--margin", help="K_o margin (default %(default)s)")
    _add_shared(p, "--stiffer-by")
    p.add_argument(
        "--paper",
        action="store_true",
        help="the paper's local model only, without own-force compensation (what a contact "
        "coupled to another user's gets)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_gains)


#: The grid of ``haptic gains-table`` (docs/gains-table.json, the README's table).
GAINS_TABLE_GRID = {
    "local_model": ("p", "pi"),
    "sim_rate_hz": (10.0, 20.0, 50.0, 100.0),
    "delay_ticks": (0, 2, 4),
    "k_o": (100.0, 300.0, 1000.0, 3000.0),
}


def _table_row(
    job: tuple[str, float, int, float, str, float, bool, float | None],
) -> dict[str, object]:
    """One row of ``haptic gains-table`` (a worker's job)."""
    mode, rate, delay, k_o, profile, margin, paper, stiffer_by = job
    d = _profile_design(
        profile,
        k_o,
        paper=paper,
        stiffer_by=stiffer_by,
        sim_rate_hz=rate,
        delay_ticks=delay,
        mode=mode,
        margin=margin,
    )
    keep = ("k_h", "i_gain", "b_h", "proxy_hold", "own_gain", "worst_spectral_radius")
    row: dict[str, object] = {"local_model": mode, "sim_rate_hz": rate, "delay_ticks": delay}
    row.update({"k_o": k_o, **{k: v for k, v in d.to_json().items() if k in keep}})
    row.update(
        felt_stiffness_ratio_1hz=d.felt_stiffness_ratio_1hz,
        felt_stiffness_ratio_8hz=d.felt_stiffness_ratio_8hz,
        design_ms=d.design_ms,
        designed_as="pi" if d.i_gain > 0.0 else "p",
    )
    return row


def _cmd_ship_table(args: argparse.Namespace) -> int:
    """``haptic gains-table --ship``: build (or complete) a profile's shipped table;
    ``--cache``: the same grid for this device (a profile, or ``--max-stiffness`` and
    ``--max-damping``) into the client's cache of designs (client.gain_store)."""
    from haptic_collab.cli.shipped_tables import shipped_dir
    from haptic_collab.client.devices.profiles import get_sim_profile
    from haptic_collab.client.gain_build import build_table, progress_bar
    from haptic_collab.client.gain_store import cache_path
    from haptic_collab.shared.gains.table_file import design_code_hash

    try:
        lim = get_sim_profile(args.profile).limits
    except ValueError as exc:
        raise CliError(str(exc)) from None
    k_h_max, b_h_max = lim.max_stiffness_n_per_m, lim.max_damping_n_s_per_m
    label = args.profile
    if args.max_stiffness is not None or args.max_damping is not None:
        if args.ship:
            raise CliError("--ship builds a built-in profile's table: use --cache for a device")
        if args.max_stiffness is None or args.max_damping is None:
            raise CliError("give both --max-stiffness and --max-damping")
        k_h_max, b_h_max = args.max_stiffness, args.max_damping
        label = f"K_h<={k_h_max:g} B_h<={b_h_max:g}"
    if args.out:
        out = Path(args.out)
    elif args.cache:
        out = cache_path(design_code_hash())
        out.parent.mkdir(parents=True, exist_ok=True)
    else:
        out = shipped_dir() / f"{args.profile}.json"
    done, left = build_table(
        label,
        k_h_max,
        b_h_max,
        out=out,
        workers=args.workers,
        max_jobs=args.max_jobs,
        progress=progress_bar(label),
        remember_undesignable=args.cache and not args.out,
    )
    print(f"{out}: {done} cells designed now; {left} left for a later run")
    return 0


def _cmd_gains_table(args: argparse.Namespace) -> int:
    from concurrent.futures import ProcessPoolExecutor

    if args.ship or args.cache:
        return _cmd_ship_table(args)

    from haptic_collab.client.devices.profiles import get_sim_profile
    from haptic_collab.shared.gains.policy import STIFFER_BY

    try:
        lim = get_sim_profile(args.profile).limits
    except KeyError as exc:
        raise CliError(str(exc).strip("'\"")) from None
    g = GAINS_TABLE_GRID
    jobs = [
        (m, r, d, k, args.profile, args.margin, args.paper, args.stiffer_by)
        for m in g["local_model"]
        for r in g["sim_rate_hz"]
        for d in g["delay_ticks"]
        for k in g["k_o"]
    ]
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        rows = list(pool.map(_table_row, jobs))
    out = {
        "profile": f"{args.profile} (K_h <= {lim.max_stiffness_n_per_m:g} N/m, "
        f"B_h <= {lim.max_damping_n_s_per_m:g} N*s/m)",
        "margin": args.margin,
        "stiffer_by": STIFFER_BY if args.stiffer_by is None else args.stiffer_by,
        "own_force": not args.paper,
        "rows": rows,
    }
    text = json.dumps(out, indent=1) + "\n"
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
    else:
        print(text, end="")
    return 0


def _add_gains_table(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "gains-table",
        help="the product's gain designs over a grid of K_o, rates and delays (JSON)",
        description="Design the local model for K_o 100-3000 N/m, simulation rates 10-100 Hz and "
        "0-4 ticks of delay, P and PI, as `haptic gains` does for one (docs/gains-table.json).",
    )
    _add_shared(
        p,
        "--profile",
        help="device profile whose limits bound K_h and B_h (default %(default)s)",
    )
    _add_shared(p, "--margin", help="K_o margin (default %(default)s)")
    _add_shared(p, "--stiffer-by")
    p.add_argument("--paper", action="store_true", help="without own-force compensation")
    p.add_argument("--workers", type=_whole_positive, default=2, help="design processes")
    p.add_argument("--out", help="write the JSON here instead of printing it")
    p.add_argument(
        "--ship",
        action="store_true",
        help="build the profile's shipped table instead (shared/gains/tables/PROFILE.json, or "
        "--out): every cell of its grid, both local models; resumes a partial file "
        "(docs/gains.md, 'Shipped tables')",
    )
    p.add_argument(
        "--cache",
        action="store_true",
        help="build the same grid for this device into the client's cache of designs "
        "($HAPTIC_GAIN_CACHE or ~/.cache/haptic-collab): a device without a shipped table "
        "then renders designed gains from its first contact too; resumes",
    )
    p.add_argument(
        "--max-stiffness",
        type=_positive,
        default=None,
        metavar="N_PER_M",
        help="with --cache: the device's largest stable stiffness [N/m] (instead of --profile)",
    )
    p.add_argument(
        "--max-damping",
        type=_nonneg,
        default=None,
        metavar="N_S_PER_M",
        help="with --cache: the device's largest virtual damping [N*s/m] (instead of --profile)",
    )
    p.add_argument(
        "--max-jobs",
        type=_whole_positive,
        default=None,
        metavar="N",
        help="with --ship or --cache: design at most N cells now (the next run goes on)",
    )
    p.set_defaults(func=_cmd_gains_table)
