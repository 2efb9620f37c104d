"""The ``haptic`` command line: one console script, one subcommand per capability.

Subcommands import their implementation lazily so that ``haptic stability`` does not pay for the
server's or the client's imports. SI units everywhere: m, N, s; stiffness N/m.

Exit status: 0 on success (whatever a stability verdict says), 2 on bad input with one clear line on
stderr (no traceback), 1 on a runtime failure.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn


class CliError(Exception):
    """Bad input: printed as one line on stderr, exit status 2."""


def _why(exc: BaseException) -> str:
    """A bad-input exception as the one line a user sees.

    A parameter class's :class:`pydantic.ValidationError` is several lines with a link; its first
    problem is ``FIELD must be BOUND, got VALUE`` (:func:`shared.checks.describe`).
    """
    from pydantic import ValidationError

    if isinstance(exc, ValidationError):
        from haptic_collab.shared.checks import describe

        return describe(exc)
    return str(exc)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def _positive(text: str) -> float:
    value = _finite(text)
    if value <= 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def _nonneg(text: str) -> float:
    value = _finite(text)
    if value < 0.0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


def _nonneg_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


def _whole_positive(text: str) -> int:
    value = _nonneg_int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text!r}")
    return value


def _probability(text: str) -> float:
    value = _finite(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {text!r}")
    return value


# ----------------------------------------------------------------------------------- shared options
#: Options that more than one subcommand takes: each one's type and default (and its help where
#: every subcommand says the same), declared once. :func:`_add_shared` adds them.
_SHARED: dict[str, dict[str, Any]] = {
    "--k-o": {"type": _positive, "required": True, "help": "object stiffness K_o [N/m]"},
    "--delay-ticks": {
        "type": _nonneg_int,
        "default": 0,
        "help": "extra simulation ticks of delay (default %(default)s)",
    },
    "--servo-rate": {"type": _positive, "default": 1000.0},
    "--sim-rate": {"type": _positive, "default": 20.0},
    "--local-model": {"choices": ["p", "pi"], "default": "pi"},
    "--profile": {"default": "phantom-desktop"},
    "--margin": {"type": _probability, "default": 0.15},
    "--stiffer-by": {
        "type": _nonneg,
        "default": None,
        "help": "the object may be this fraction stiffer than K_o: stability is checked up to "
        "(1 + it) K_o and transparency also on objects that much softer and stiffer; when not "
        "given, the product's shared.gain_key.STIFFER_BY (default: none)",
    },
    "--host": {"default": "127.0.0.1"},
    "--port": {"type": _nonneg_int, "default": 8765},
    "--mesh": {"default": "balloon"},
    "--mesh-scale": {"type": _positive, "default": None},
    "--mesh-size": {"type": _positive, "default": None},
    "--mesh-max-edge": {"type": _positive, "default": None, "metavar": "M"},
    "--material": {"default": None, "metavar": "NAME|FILE.toml"},
    "--object": {"choices": ["balloon", "fem"], "default": "balloon"},
    "--subdivisions": {"type": _nonneg_int, "default": 4},
    "--latency-ms": {"type": _nonneg, "default": 0.0, "help": "injected one-way latency [ms]"},
    "--jitter-ms": {"type": _nonneg, "default": 0.0, "help": "injected jitter [ms]"},
    "--loss": {"type": _probability, "default": 0.0},
}


#: ``--object`` of ``haptic server`` and ``haptic demo``.
_OBJECT_HELP = (
    "object model: balloon (the water balloon, default) or fem (a tetrahedral elastic solid of "
    "the mesh: soft tissue, silicone; needs the fem extra, docs/fem.md)"
)

#: ``--mesh`` of ``haptic server`` and ``haptic demo``; the names are
#: :data:`server.objects.shapes.STRESS_MESHES` (not imported here: it loads trimesh).
_MESH_HELP = (
    "'balloon', a stress shape (torus, box, plate, bowl, noisy-sphere, uneven) or a mesh file "
    "(STL, OBJ, PLY, OFF, GLB)"
)
_MESH_MAX_EDGE_HELP = (
    "refine the object (split edges at their midpoints, shape and sharp edges kept) until no "
    "edge is longer than M [m], e.g. 0.0075 for a 15 mm finger pad"
)


def _add_shared(p: argparse._ActionsContainer, flag: str, **more: Any) -> None:
    """Add the option ``flag`` of :data:`_SHARED` to ``p``; ``more`` (its help, a metavar) adds
    what the subcommand says of it (a TypeError if it tries to change what is shared)."""
    p.add_argument(flag, **_SHARED[flag], **more)


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
    """The product's design (:func:`shared.gain_design.design_gains`, timed) for K_o with the
    stiffness and damping limits of the device profile ``profile``; ``paper``: without own-force
    compensation; ``stiffer_by`` (default the product's :data:`shared.gain_key.STIFFER_BY`):
    checked up to ``(1 + stiffer_by) K_o``. Raises KeyError (unknown profile) or ValueError (as
    the design)."""
    from haptic_collab.client.devices.profiles import get_sim_profile
    from haptic_collab.shared.gain_design import design_gains
    from haptic_collab.shared.gain_key import STIFFER_BY
    from haptic_collab.workers import timed

    lim = get_sim_profile(profile).limits
    sb = STIFFER_BY if stiffer_by is None else float(stiffer_by)
    return timed(
        design_gains,
        k_o,
        k_h_max=lim.max_stiffness_n_per_m,
        b_h_max=lim.max_damping_n_s_per_m,
        own_force=not paper,
        k_o_hi=k_o * (1.0 + sb),
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
    print(
        f"  felt stiffness / K_o: {d.felt_stiffness_ratio_1hz:.3f} at 1 Hz, "
        f"{d.felt_stiffness_ratio_8hz:.3f} at 8 Hz"
    )
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
        "(1 + stiffer-by) K_o.",
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


def _cmd_gains_table(args: argparse.Namespace) -> int:
    from concurrent.futures import ProcessPoolExecutor

    from haptic_collab.client.devices.profiles import get_sim_profile
    from haptic_collab.shared.gain_key import STIFFER_BY

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
    p.set_defaults(func=_cmd_gains_table)


# ---------------------------------------------------------------------------------------- reproduce
def _cmd_reproduce(args: argparse.Namespace) -> int:
    from haptic_collab.research.plots import reproduce_figures

    results: dict[str, object] = {}
    if args.figure not in ("fig10", "fig11"):  # Fig. 7-9: the 1-D multirate simulator
        results.update(reproduce_figures(args.figure, Path(args.out)))
    if args.figure in ("fig10", "fig11", "all"):  # Fig. 10-11 need the server's 3-D object
        from haptic_collab.research.reproduce_3d import reproduce_3d

        results.update(reproduce_3d(args.figure, Path(args.out)))
    for name in results:
        print(f"wrote {Path(args.out) / (name + '.png')} and {name}.json")
    return 0


def _add_reproduce(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("reproduce", help="reproduce the paper's Fig. 7 to 11 (PNG + JSON)")
    p.add_argument("figure", choices=["fig7", "fig8", "fig9", "fig10", "fig11", "all"])
    p.add_argument("--out", default="out/figures", help="output directory")
    p.set_defaults(func=_cmd_reproduce)


# ------------------------------------------------------------------------------------------- server
def _add_stiffness_scale(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--stiffness-scale",
        type=_positive,
        default=1.0,
        metavar="S",
        help="multiply every stiffness term of the object by S (K_o scales by S; default 1)",
    )


def _cmd_server(args: argparse.Namespace) -> int:
    import asyncio
    import logging

    from haptic_collab.server.main import run_server

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    opts = _server_options(args)
    try:
        asyncio.run(run_server(opts))
    except ValueError as exc:  # bad mesh, bad parameters
        raise CliError(_why(exc)) from None
    except OSError as exc:
        raise CliError(f"cannot listen on {args.host}:{args.port}: {exc.strerror or exc}") from None
    return 0


def _server_options(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """The :class:`server.main.ServerOptions` of parsed ``haptic server`` arguments."""
    from haptic_collab.server.main import ServerOptions

    return ServerOptions(
        host=args.host,
        port=args.port,
        mesh=args.mesh,
        mesh_scale=args.mesh_scale,
        mesh_size=args.mesh_size,
        mesh_max_edge=args.mesh_max_edge,
        sim_rate_hz=args.sim_rate,
        latency_ms=args.latency_ms,
        jitter_ms=args.jitter_ms,
        loss=args.loss,
        seed=args.seed,
        primitive=args.primitive,
        damping=args.damping,
        stiffness_scale=args.stiffness_scale,
        subdivisions=args.subdivisions,
        duration_s=args.duration,
        token_file=args.token_file,
        token=args.token,
        allow_origins=tuple(args.allow_origin),
        tls_cert=args.tls_cert,
        tls_key=args.tls_key,
        insecure=args.insecure,
        material=args.material,
        object=args.object,
        volume_cache=args.volume_cache,
    )


def _add_server(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("server", help="run the authoritative server (object, simulation, viewer)")
    p.add_argument(
        "--config",
        default=None,
        metavar="FILE.toml",
        help="defaults for every option below from a TOML file (flags given here override it; "
        "docs/server-config.example.toml)",
    )
    _add_shared(p, "--host")
    _add_shared(p, "--port", help="TCP port (0: any free port)")
    _add_shared(p, "--mesh", help=_MESH_HELP)
    _add_shared(p, "--object", help=_OBJECT_HELP)
    _add_shared(
        p,
        "--material",
        help="object material: water-balloon, silicone-ball, soft-tissue or a TOML file "
        "(docs/materials.md; default: the built-in silicone-like balloon); with --object fem: "
        "liver, skin, ecoflex-0030, sylgard-184 or a TOML file (docs/fem.md; default liver)",
    )
    p.add_argument(
        "--volume-cache",
        default=None,
        metavar="DIR",
        help="folder of cached FEM volume meshes (default ~/.cache/haptic-collab/volumes)",
    )
    _add_shared(p, "--mesh-scale", help="multiply the file's coordinates by S")
    _add_shared(p, "--mesh-size", help="rescale so the largest extent is this [m]")
    _add_shared(p, "--mesh-max-edge", help=_MESH_MAX_EDGE_HELP)
    _add_shared(p, "--subdivisions", help="icosphere subdivisions of the balloon")
    _add_shared(p, "--sim-rate", help="simulation rate [Hz]")
    p.add_argument(
        "--damping", type=_nonneg, default=None, help="object damping (visco-elastic, eq. 9)"
    )
    _add_stiffness_scale(p)
    p.add_argument(
        "--primitive", choices=["plane", "sphere"], default="plane", help="local model primitive"
    )
    _add_shared(p, "--latency-ms")
    _add_shared(p, "--jitter-ms")
    _add_shared(p, "--loss", help="injected loss of state frames [0, 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the latency injection")
    p.add_argument("--duration", type=_positive, default=None, help="stop after this many seconds")
    sec = p.add_argument_group("security (docs/security.md)")
    sec.add_argument(
        "--token-file",
        default=None,
        metavar="FILE",
        help="accepted tokens, one per line: TOKEN ROLE [NAME] (role user or viewer; NAME binds)",
    )
    sec.add_argument("--token", default=None, help="one accepted token, role user (may also watch)")
    sec.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="ORIGIN",
        help="browser origin allowed besides the server's own, e.g. https://lab.example (repeat)",
    )
    sec.add_argument("--tls-cert", default=None, metavar="PEM", help="serve https and wss")
    sec.add_argument("--tls-key", default=None, metavar="PEM", help="the certificate's key")
    sec.add_argument(
        "--insecure",
        action="store_true",
        help="listen off loopback without tokens (anyone who can reach it may push)",
    )
    p.set_defaults(func=_cmd_server)


# ------------------------------------------------------------------------------------------- client
def _trajectory_options(text: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"expected key=value, got {item!r}")
        out[key.strip()] = _finite(value)
    return out


def _anchor_option(text: str) -> str:
    from haptic_collab.client.app import check_anchor

    try:
        return check_anchor(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def _cmd_client(args: argparse.Namespace) -> int:
    import asyncio

    from haptic_collab.client.app import run_client
    from haptic_collab.client.servo_process import ServoProcessError

    _configure_logging(args)
    opts = _client_options(args)
    try:
        summary = asyncio.run(run_client(opts))
    except (ValueError, ConnectionError) as exc:  # DeviceError too: before any network
        raise CliError(_why(exc)) from None
    except ServoProcessError as exc:  # the servo process died (summary and recording written)
        raise CliError(_why(exc)) from None
    except OSError as exc:  # e.g. the --record file cannot be created
        raise CliError(_why(exc)) from None
    rate, rtt = summary.get("servo_rate_hz"), summary.get("rtt_ms_p50")
    print(
        f"{opts.name}: servo {'-' if rate is None else f'{rate:.1f}'} Hz, "
        f"max force {summary.get('max_force_n', 0.0):.2f} N, patches {summary['patches']}, "
        f"rtt p50 {'-' if rtt is None else f'{rtt:.1f}'} ms"
    )
    return 0


def _hand_trajectory_options(args: argparse.Namespace) -> dict[str, float]:
    """``--hand-*`` values as :data:`client.devices.HAND_OPTIONS` keys (only those given)."""
    given = {
        "hand_mass_kg": args.hand_mass,
        "hand_stiffness_n_per_m": args.hand_stiffness,
        "hand_damping_n_s_per_m": args.hand_damping,
    }
    return {k: v for k, v in given.items() if v is not None}


def _client_options(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """The :class:`client.app.ClientOptions` of parsed ``haptic client`` arguments.

    The ``--hand-*`` flags travel in the trajectory options (the simulated hand pulls the device
    along the trajectory); :func:`client.devices.make_device` takes them out into the hand.
    """
    from haptic_collab.client.app import ClientOptions

    return ClientOptions(
        url=args.url,
        name=args.name,
        device=args.device,
        profile=args.profile,
        local_model=args.local_model,
        servo_rate_hz=args.servo_rate,
        record=Path(args.record) if args.record else None,
        summary=Path(args.summary) if args.summary else None,
        duration_s=args.duration,
        anchor=args.anchor,
        trajectory={**args.trajectory, **_hand_trajectory_options(args)},
        theta_m=args.theta_mm / 1000.0,
        theta_mode=args.theta_mode,
        passivity=args.passivity,
        margin=args.margin,
        hid_profile=args.hid_profile,
        stop_on_signals=True,
        token=args.token,
        ca_file=args.ca_file,
        gains=args.gains,
        engage=args.engage,
        servo=args.servo,
    )


def _add_hand(p: argparse.ArgumentParser) -> None:
    """``--hand-mass``, ``--hand-stiffness``, ``--hand-damping``: the simulated hand's own values."""
    p.add_argument(
        "--hand-mass",
        type=_nonneg,
        default=None,
        metavar="KG",
        help="simulated hand mass [kg] (default 0.45; the device's 0.045 kg is added)",
    )
    p.add_argument(
        "--hand-stiffness",
        type=_positive,
        default=None,
        metavar="N_PER_M",
        help="simulated hand stiffness [N/m] (default 300)",
    )
    p.add_argument(
        "--hand-damping",
        type=_nonneg,
        default=None,
        metavar="N_S_PER_M",
        help="simulated hand damping [N*s/m] (default 5; the device's own is added)",
    )


def _add_client(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("client", help="run one haptic user: device, 1 kHz servo loop, link")
    p.add_argument("--url", default="ws://127.0.0.1:8765/ws")
    p.add_argument("--name", default="A", help="user name shown to others")
    p.add_argument(
        "--device", default="sim:press", help="sim:press | sim:rest | sim:replay:FILE | hid:VID:PID"
    )
    _add_shared(p, "--profile", help="simulated device profile (see haptic devices)")
    p.add_argument(
        "--hid-profile", default=None, help="generic HID device profile (name or JSON file)"
    )
    _add_shared(p, "--local-model")
    _add_shared(p, "--servo-rate", help="servo rate [Hz]")
    p.add_argument("--record", default=None, help="write the servo telemetry CSV here")
    p.add_argument("--summary", default=None, help="write a JSON summary here")
    p.add_argument("--duration", type=_positive, default=None, help="run this many seconds")
    p.add_argument(
        "--anchor",
        type=_anchor_option,
        default="auto",
        help="where the hand works: auto, top, side (by join order) or side:N (the server's "
        "N-th side, those a press on the top moves most first)",
    )
    p.add_argument(
        "--trajectory",
        type=_trajectory_options,
        default={},
        help="scripted hand options, e.g. delay_s=4,depth_m=0.02,hold_s=6",
    )
    p.add_argument(
        "--theta-mm", type=_nonneg, default=1.0, help="integration threshold theta (eq. 17) [mm]"
    )
    p.add_argument(
        "--gains",
        choices=["server", "local"],
        default="server",
        help="render the server's recommended gains when they fit this device and no better "
        "design of its own is ready (server), or always design them here (local) "
        "(default %(default)s)",
    )
    p.add_argument(
        "--engage",
        choices=["default", "button", "auto"],
        default="default",
        help="how forces come on: with the device's first button (button: a press engages, the "
        "next disengages, as vendor examples do), with the first checked patch (auto), or button "
        "for a device that has buttons and auto otherwise (default %(default)s)",
    )
    p.add_argument(
        "--servo",
        choices=["auto", "process", "thread"],
        default="auto",
        help="run the 1 kHz servo loop (device, local model, safety) in a process of its own, "
        "off the network link's interpreter lock (process), or in a thread of the client "
        "(thread); auto = process (default %(default)s)",
    )
    p.add_argument(
        "--theta-mode",
        choices=["auto", "fixed", "variable"],
        default="auto",
        help="threshold: fixed (eq. 17) or variable (eq. 18); auto = variable for PI, fixed for P "
        "(default %(default)s)",
    )
    p.add_argument(
        "--passivity",
        choices=["auto", "on", "off"],
        default="auto",
        help="time-domain passivity controller at the device port; auto = on for PI "
        "(default %(default)s)",
    )
    _add_shared(p, "--margin", help="K_o margin of the gain design (default %(default)s)")
    p.add_argument(
        "--token",
        default=None,
        help="the server's token (default: $HAPTIC_TOKEN; prefer the variable: it stays out of ps)",
    )
    p.add_argument(
        "--ca-file",
        default=None,
        metavar="PEM",
        help="trust this CA for a wss:// server (default: the system's CAs)",
    )
    _add_hand(p)
    p.set_defaults(func=_cmd_client)


# ------------------------------------------------------------------------------------------ devices
def _cmd_devices(args: argparse.Namespace) -> int:
    from haptic_collab.client.devices import list_devices

    devices = list_devices()
    if args.json:
        print(json.dumps(devices, indent=2))
        return 0
    backends = [d for d in devices if d.get("kind") == "backend"]
    sims = [d for d in devices if d.get("kind") == "sim"]
    hid = [d for d in devices if d.get("backend") == "hid"]
    print("Simulated devices (--device sim:press|sim:rest|sim:replay:FILE --profile NAME):")
    for d in {d["profile"]: d for d in sims}.values():
        print(
            f"  {d['profile']:<16} max force {d['max_force_n']:.1f} N, "
            f"max stiffness {d['max_stiffness_n_per_m']:.0f} N/m"
        )
    print("HID devices (--device hid:VID:PID):")
    if not hid:
        print("  none found")
    for d in hid:
        print(
            f"  {d.get('spec', '?'):<16} {d.get('manufacturer', '')} {d.get('product', '')}".rstrip()
        )
    print("Device backends (--device NAME:ARGS; docs/devices.md says how to add one):")
    for b in backends:
        what = b["description"] if b["available"] else f"not available: {b['message']}"
        print(f"  {b['name']:<16} {what}".rstrip())
        if b["name"] not in ("sim", "hid"):  # their devices are listed above
            for d in b["devices"]:
                print(f"  {'':<16} {d.get('spec', '?')}")
    return 0


def _add_devices(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "devices", help="list device backends, HID devices and simulated device profiles"
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_devices)


# --------------------------------------------------------------------------------------------- plot
def _cmd_plot(args: argparse.Namespace) -> int:
    from haptic_collab.client.recorder import plot_recording

    files = [Path(f) for f in args.files]
    out = Path(args.out) if args.out else files[0].with_suffix(".png")
    try:
        plot_recording(files, out)
    except ImportError as exc:
        raise CliError(
            f"plotting needs matplotlib ({exc}): pip install 'haptic-collab[plots]'"
        ) from None
    except (ValueError, OSError) as exc:
        raise CliError(_why(exc)) from None
    print(f"wrote {out}")
    return 0


def _add_plot(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "plot",
        help="draw --record files: probe and proxy along the contact normal, and the force",
        description="Draw one or more `haptic client --record` CSV files like the demo plot: per "
        "file, probe and proxy along the contact normal [mm]; then the force on each user [N].",
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="--record CSV file(s)")
    p.add_argument(
        "--out", default=None, metavar="PNG", help="PNG to write (default: FILE with .png)"
    )
    p.set_defaults(func=_cmd_plot)


# ----------------------------------------------------------------------------------------- protocol
def _cmd_protocol(args: argparse.Namespace) -> int:
    from haptic_collab.shared.protocol import json_schema

    print(json.dumps(json_schema(args.direction), indent=2))
    return 0


def _add_protocol(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from haptic_collab.shared.protocol import SCHEMA_DIRECTIONS

    p = sub.add_parser(
        "protocol",
        help="print the wire protocol's JSON Schema",
        description="Print one JSON Schema (draft 2020-12) of the JSON text frames: every message "
        "and nested model in $defs, and a top-level oneOf of the messages, discriminated by "
        "`type`. Validate a frame against it as is; docs/protocol.md describes the binary frames.",
    )
    p.add_argument("--schema", action="store_true", help="print the JSON Schema (the default)")
    p.add_argument(
        "--direction",
        choices=SCHEMA_DIRECTIONS,
        default="both",
        help="which messages the top-level oneOf admits: both directions, client -> server only "
        "(hello, state, ping, bye) or server -> client only (welcome, patch, pong, error, room) "
        "(default %(default)s)",
    )
    p.set_defaults(func=_cmd_protocol)


# -------------------------------------------------------------------------------------------- bench
def _cmd_bench(args: argparse.Namespace) -> int:
    results: dict[str, object] = {}
    if args.what in ("server", "all"):
        from haptic_collab.bench.world import measure as bench_server

        results["server"] = bench_server()
    if args.what in ("servo", "all"):
        from haptic_collab.bench.servo import run as bench_servo

        results["servo"] = bench_servo(duration_s=args.duration, rate_hz=args.servo_rate)
    if args.what in ("gains", "all"):
        from haptic_collab.bench.gains import run as bench_gains

        results["gains"] = bench_gains()
    if args.what == "fidelity":
        if args.plot:
            _need_matplotlib()
        from haptic_collab.bench.fidelity import plot as plot_fidelity
        from haptic_collab.bench.fidelity import run as bench_fidelity
        from haptic_collab.research.fidelity_1d import RunOptions

        try:
            fid_options = RunOptions(
                jitter_s=args.jitter_us * 1e-6, quantum_m=args.quantum_um * 1e-6, seed=args.seed
            )
        except ValueError as exc:
            raise CliError(_why(exc)) from None
        results["fidelity"] = fid = bench_fidelity(
            quick=args.quick,
            options=fid_options,
            seed=args.seed,
            workers=args.workers,
            include_3d=not (args.no_3d or args.quick),
            log=lambda msg: print(msg, file=sys.stderr, flush=True),
        )
        if args.plot:
            for path in plot_fidelity(fid, Path(args.plot)):
                print(f"wrote {path}", file=sys.stderr)
        if not args.json and not args.out:
            _print_fidelity_table(fid)
            return 0
    if args.what == "load":
        from haptic_collab.bench.load import LoadOptions, subdivisions_for_vertices
        from haptic_collab.bench.load import run as bench_load

        try:
            subdivisions = (
                subdivisions_for_vertices(args.vertices)
                if args.vertices is not None
                else args.subdivisions
            )
            load_opts = LoadOptions(
                users=args.users,
                viewers=args.viewers,
                duration_s=args.duration,
                sim_rate_hz=args.sim_rate,
                subdivisions=subdivisions,
                workers=args.workers or 4,
            )
            results["load"] = bench_load(
                load_opts, log=lambda msg: print(msg, file=sys.stderr, flush=True)
            )
        except (ValueError, RuntimeError) as exc:
            raise CliError(_why(exc)) from None
    payload = results if args.what == "all" else results[args.what]
    text = json.dumps(payload, indent=2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    print(text if args.json or not args.out else f"wrote {args.out}")
    return 0


def _add_bench(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "bench",
        help="measure speed (JSON): server tick cost, servo loop timing, gain lookups; "
        "'fidelity': every rendering scheme side by side; 'load': users and viewers against a "
        "server process",
    )
    p.add_argument("what", choices=["server", "servo", "gains", "fidelity", "load", "all"])
    p.add_argument("--json", action="store_true", help="print JSON (always JSON; kept for scripts)")
    p.add_argument("--out", default=None, help="also write the JSON here")
    p.add_argument(
        "--duration",
        type=_positive,
        default=5.0,
        help="servo bench duration; load: the measurement window after warm-up [s] "
        "(default %(default)s)",
    )
    _add_shared(p, "--servo-rate", help="servo bench rate [Hz]")
    p.add_argument(
        "--quick", action="store_true", help="fidelity: the documented subset (< 2 min, 2 cores)"
    )
    p.add_argument("--plot", default=None, metavar="DIR", help="fidelity: write the plots here")
    p.add_argument("--seed", type=int, default=0, help="fidelity: recorded seed (deterministic)")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="fidelity: worker processes (default: cores); load: client processes (default 4)",
    )
    p.add_argument(
        "--no-3d",
        action="store_true",
        help="fidelity: skip the 3-D World cells (--quick skips them too)",
    )
    p.add_argument(
        "--jitter-us",
        type=float,
        default=0.0,
        help="fidelity: servo wake-up jitter [us], each tick up to this early or late (default 0)",
    )
    p.add_argument(
        "--quantum-um",
        type=float,
        default=0.0,
        help="fidelity: encoder resolution [um] (Phantom Desktop: 23; default 0: exact)",
    )
    p.add_argument(
        "--users",
        type=_nonneg_int,
        default=32,
        help="load: websocket users, at most 32 (default %(default)s)",
    )
    p.add_argument(
        "--viewers",
        type=_nonneg_int,
        default=8,
        help="load: websocket viewers (default %(default)s)",
    )
    _add_shared(p, "--sim-rate", help="load: simulation rate [Hz] (default %(default)s)")
    _add_shared(
        p,
        "--subdivisions",
        help="load: icosphere subdivisions of the balloon (default %(default)s: 2562 vertices)",
    )
    p.add_argument(
        "--vertices",
        type=_nonneg_int,
        default=None,
        help="load: the balloon's vertex count instead (2562, 10242, 40962, ...)",
    )
    p.set_defaults(func=_cmd_bench)


def _print_fidelity_table(result: dict[str, object]) -> None:
    """A human-readable summary of ``haptic bench fidelity`` (``--json`` for everything)."""
    summary = result["summary"]
    assert isinstance(summary, dict)

    def pct(v: object) -> str:
        return f"{v:8.1%}" if isinstance(v, float) else f"{'-':>8s}"

    print(
        f"{'scheme':17s} {'stable':>8s} {'unseen':>8s} {'~best':>8s} {'~best':>8s} "
        f"{'per hand':>8s} {'outside':>8s}"
    )
    print(
        f"{'':17s} {'(box)':>8s} {'(box)':>8s} {'spring':>8s} {'unseen':>8s} "
        f"{'~best':>8s} {'stable':>8s}"
    )
    for s in result["schemes"]:  # type: ignore[attr-defined]
        row = summary[s]
        print(
            f"{s:17s} {pct(row['box_stable_fraction'])} {pct(row['box_stable_fraction_unseen'])} "
            f"{pct(row['near_best_fraction_box_spring'])} "
            f"{pct(row['near_best_fraction_box_unseen'])} "
            f"{pct(row['per_hand_near_best_fraction'])} {pct(row['outside_stable_fraction'])}"
        )
    prod = summary["product"]
    print(
        f"~best: within the stiffness JND ({summary['stiffness_jnd']:.0%}) of the best scheme "
        f"stable with every hand of the box, over {summary['conditions']} conditions"
    )
    print(
        f"the product (local-p or local-pi): box-stable in {pct(prod['box_stable_fraction'])}, "
        f"~best on the spring in {pct(prod['near_best_fraction_box_spring'])}, on the objects "
        f"the design did not see in {pct(prod['near_best_fraction_box_unseen'])}; a peer "
        f"better in {len(prod['peer_better'])} conditions"
    )


def _cmd_demo(args: argparse.Namespace) -> int:
    from haptic_collab.demo import DemoOptions, run_demo

    if args.plot:
        _need_matplotlib()  # before the run, not after it

    opts = DemoOptions(
        duration_s=args.duration,
        headless=args.headless,
        report=Path(args.report) if args.report else None,
        plot=Path(args.plot) if args.plot else None,
        sim_rate_hz=args.sim_rate,
        servo_rate_hz=args.servo_rate,
        latency_ms=args.latency_ms,
        jitter_ms=args.jitter_ms,
        loss=args.loss,
        mesh=args.mesh,
        port=args.port,
        host=args.host,
        local_model=args.local_model,
        workdir=Path(args.workdir) if args.workdir else None,
        stiffness_scale=args.stiffness_scale,
        material=args.material,
        object=args.object,
        mesh_scale=args.mesh_scale,
        mesh_size=args.mesh_size,
        mesh_max_edge=args.mesh_max_edge,
        hand_mass_kg=args.hand_mass,
        hand_stiffness_n_per_m=args.hand_stiffness,
        hand_damping_n_s_per_m=args.hand_damping,
        log_level=getattr(args, "log_level", "info"),
        reference_loop=args.reference_loop,
    )
    try:
        run_demo(opts)
    except ValueError as exc:
        raise CliError(_why(exc)) from None
    except RuntimeError as exc:
        print(f"haptic demo: failed: {exc}", file=sys.stderr)
        return 1
    return 0


def _add_demo(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("demo", help="server + two simulated users on a shared water balloon")
    p.add_argument("--duration", type=_positive, default=20.0, help="run length [s] (>= 12)")
    p.add_argument("--headless", action="store_true", help="do not open a browser")
    p.add_argument("--report", default=None, help="write the JSON report here")
    p.add_argument("--plot", default=None, help="write a PNG of probe, proxy and force here")
    p.add_argument(
        "--reference-loop",
        action="store_true",
        help="run a do-nothing 1 kHz loop beside the users and report its timing next to "
        "theirs (what this machine gives any loop; it takes about a third of a core)",
    )
    _add_shared(p, "--sim-rate", help="simulation rate [Hz]")
    _add_shared(p, "--servo-rate", help="servo rate [Hz]")
    _add_shared(p, "--latency-ms")
    _add_shared(p, "--jitter-ms")
    _add_shared(p, "--loss", help="injected loss of state frames")
    _add_shared(p, "--mesh", help=_MESH_HELP)
    _add_shared(p, "--mesh-scale", help="multiply the mesh file's coordinates by S")
    _add_shared(
        p, "--mesh-size", metavar="M", help="rescale the mesh file so its largest extent is M [m]"
    )
    _add_shared(p, "--mesh-max-edge", help=_MESH_MAX_EDGE_HELP)
    _add_shared(p, "--object", help=_OBJECT_HELP)
    _add_shared(
        p,
        "--material",
        help="object material: water-balloon, silicone-ball, soft-tissue or a TOML file; with "
        "--object fem: liver, skin, ecoflex-0030, sylgard-184 or a TOML file",
    )
    _add_shared(p, "--port", help="server port (0: any free port)")
    _add_shared(
        p,
        "--host",
        help="server address (0.0.0.0: every interface; the viewer URLs of this machine are "
        "printed; default %(default)s)",
    )
    _add_shared(p, "--local-model")
    p.add_argument("--workdir", default=None, help="keep logs and telemetry here")
    _add_stiffness_scale(p)
    _add_hand(p)
    p.set_defaults(func=_cmd_demo)


# -------------------------------------------------------------------------------------------- main
#: ``--log-level`` choices (Python logging levels).
LOG_LEVELS = ("debug", "info", "warning", "error")
#: Subcommands that log (and take ``--log-level`` after their name as well as before).
_LOGGING_COMMANDS = ("server", "client", "demo")


def _configure_logging(args: argparse.Namespace) -> None:
    """Log to stderr at ``--log-level`` (default info) with time, logger name and level."""
    import logging

    level = getattr(logging, str(getattr(args, "log_level", "info")).upper(), logging.INFO)
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger().setLevel(level)


def _add_log_level(p: argparse.ArgumentParser, *, top: bool) -> None:
    if "--log-level" in p._option_string_actions:
        return
    p.add_argument(
        "--log-level",
        choices=LOG_LEVELS,
        # after the subcommand it overrides the top-level value only when given
        default="info" if top else argparse.SUPPRESS,
        help="log verbosity of server, client and demo (default info)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``haptic`` argument parser with every subcommand."""
    parser = _Parser(
        prog="haptic", description="Multirate haptic collaboration on a shared deformable object."
    )
    _add_log_level(parser, top=True)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_stability(sub)
    _add_gains(sub)
    _add_gains_table(sub)
    _add_reproduce(sub)
    for extra in _EXTRA:
        extra(sub)
    for name in _LOGGING_COMMANDS:
        if name in sub.choices:
            _add_log_level(sub.choices[name], top=False)
    return parser


_EXTRA = [_add_server, _add_client, _add_demo, _add_devices, _add_plot, _add_protocol, _add_bench]


def _need_matplotlib() -> None:
    """Raise :class:`CliError` when the ``plots`` extra (matplotlib) is not installed."""
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        raise CliError("--plot needs matplotlib: pip install 'haptic-collab[plots]'")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``haptic`` console script; returns the exit status."""
    # One BLAS thread: the simulation tick measured faster that way on a busy machine, and a client's
    # BLAS threads must not compete with its servo thread. Set before numpy is first imported.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "server" and getattr(args, "config", None):
        from haptic_collab.server.config import ConfigError, apply_server_config

        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        try:
            apply_server_config(sub.choices["server"], args.config)
        except ConfigError as exc:
            print(f"haptic server: error: {exc}", file=sys.stderr)
            return 2
        args = parser.parse_args(argv)  # flags given explicitly override the file
    if args.command in _LOGGING_COMMANDS:
        _configure_logging(args)  # before the subcommand's own basicConfig (then a no-op)
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"haptic {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:
        if exc.name is None or exc.name.split(".")[0] != "matplotlib":
            raise
        print(
            f"haptic {args.command}: error: the figures need matplotlib: "
            "pip install 'haptic-collab[plots]'",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
