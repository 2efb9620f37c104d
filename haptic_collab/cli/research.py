"""The research and tooling subcommands: ``haptic reproduce``, ``plot``, ``protocol`` and ``bench``.

Each command's handler (``_cmd_*``) and parser (``_add_*``), and the human-readable table of
``haptic bench fidelity``. The figures, the benchmarks and the research drivers (matplotlib among
them) are imported inside the handlers, so that they stay off every other command's start-up path.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

from haptic_collab.cli.args import (
    CliError,
    _add_shared,
    _need_matplotlib,
    _nonneg_int,
    _positive,
    _why,
)
from haptic_collab.shared.extras import install_hint
from haptic_collab.shared.gains.policy import HOLD_BACK_S as REST_HOLD_BACK_S


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


# --------------------------------------------------------------------------------------------- plot
def _cmd_plot(args: argparse.Namespace) -> int:
    from haptic_collab.client.recorder import plot_recording

    files = [Path(f) for f in args.files]
    out = Path(args.out) if args.out else files[0].with_suffix(".png")
    try:
        plot_recording(files, out)
    except ImportError as exc:
        raise CliError(f"plotting needs matplotlib ({exc}): {install_hint('plots')}") from None
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
def _or(value: float | None, default: float) -> float:
    return default if value is None else value


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
        from haptic_collab.research.fidelity_cases import RunOptions
        from haptic_collab.shared.gains.policy import DESIGN_MARGIN, STIFFER_BY

        try:
            fid_options = RunOptions(
                jitter_s=args.jitter_us * 1e-6,
                quantum_m=args.quantum_um * 1e-6,
                seed=0 if args.seed is None else args.seed,
            )
        except ValueError as exc:
            raise CliError(_why(exc)) from None
        results["fidelity"] = fid = bench_fidelity(
            quick=args.quick,
            options=fid_options,
            seed=0 if args.seed is None else args.seed,
            workers=args.workers,
            include_3d=not (args.no_3d or args.quick),
            design_reached=args.design_reached,
            design_margin=_or(args.design_margin, DESIGN_MARGIN),
            design_stiffer_by=_or(args.design_stiffer_by, STIFFER_BY),
            plane_check_s=args.plane_check_s,
            rest_plane=not args.no_rest_plane,
            rest_hold_back_s=args.rest_hold_back_s,
            log=lambda msg: print(msg, file=sys.stderr, flush=True),
        )
        if args.plot:
            for path in plot_fidelity(fid, Path(args.plot)):
                print(f"wrote {path}", file=sys.stderr)
        if not args.json and not args.out:
            _print_fidelity_table(fid)
            return 0
    if args.what == "drawn":
        from haptic_collab.bench.drawn import run_drawn

        if args.conditions < 1 or args.hands < 1:
            raise CliError("--conditions and --hands must be at least 1")
        results["drawn"] = drawn = run_drawn(
            args.seed,
            args.conditions,
            hands=args.hands,
            workers=args.workers,
            log=lambda msg: print(msg, file=sys.stderr, flush=True),
        )
        print(f"drawn: seed {drawn['seed']}", file=sys.stderr, flush=True)
        if not args.json and not args.out:
            _print_drawn_table(drawn)
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
    if args.what == "rooms":  # its own options: python -m haptic_collab.bench.rooms --help
        from haptic_collab.bench.rooms import parse as rooms_options
        from haptic_collab.bench.rooms import print_slowest
        from haptic_collab.bench.rooms import run as bench_rooms

        if args.rooms < 2:
            raise CliError(
                f"--rooms must be at least 2 (a FEM room and a balloon room), got {args.rooms}"
            )
        argv = ["--duration-s", str(args.duration), "--rooms", str(args.rooms)]
        try:
            rooms_result = bench_rooms(rooms_options(argv))
        except RuntimeError as exc:
            raise CliError(_why(exc)) from None
        results["rooms"] = rooms_result
        print_slowest(rooms_result)
    if args.what == "fem-gravity":  # python -m haptic_collab.bench.fem_gravity for its options
        from haptic_collab.bench.fem_gravity import bench_fem_gravity

        results["fem-gravity"] = bench_fem_gravity()
    payload = results if args.what == "all" else results[args.what]
    text = json.dumps(payload, indent=2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    print(text if args.json or not args.out else f"wrote {args.out}")
    return 0


#: Each benchmark of ``haptic bench`` and what it measures (its own subcommand, its own options).
BENCHES: dict[str, str] = {
    "server": "the simulation tick's cost (World.tick) by mesh size and users",
    "servo": "the servo loop's timing at its rate",
    "gains": "gain-table lookups and one cell's design",
    "fidelity": "every rendering scheme side by side on the fidelity grid (docs/fidelity.md)",
    "drawn": "the product's own client on objects, delays and partners drawn at random from the "
    "declared set (docs/stability.md); prints its seed",
    "load": "users and viewers against a server process for minutes (docs/bench-load.md)",
    "rooms": "a FEM room beside balloon rooms, one process vs a process per room (its own "
    "options: python -m haptic_collab.bench.rooms --help)",
    "fem-gravity": "the FEM solid's sag and start-up with and without --gravity (docs/fem.md)",
    "all": "server, servo and gains",
}
#: The options each benchmark takes besides --json and --out (the others keep their defaults).
_BENCH_OPTIONS: dict[str, tuple[str, ...]] = {
    "server": (),
    "servo": ("--duration", "--servo-rate"),
    "gains": (),
    "fidelity": (
        "--quick", "--plot", "--seed", "--workers", "--no-3d", "--design-reached",
        "--design-margin", "--design-stiffer-by", "--plane-check-s", "--rest-hold-back-s",
        "--no-rest-plane", "--jitter-us", "--quantum-um",
    ),
    "drawn": ("--seed", "--conditions", "--hands", "--workers"),
    "load": (
        "--duration", "--workers", "--users", "--viewers", "--sim-rate", "--subdivisions",
        "--vertices",
    ),
    "rooms": ("--duration", "--rooms"),
    "fem-gravity": (),
    "all": ("--duration", "--servo-rate"),
}  # fmt: skip
#: A benchmark's own default of a shared option (the option is copied for it).
_BENCH_DEFAULTS: dict[str, dict[str, object]] = {"rooms": {"--duration": 20.0}}


def _bench_options(p: argparse.ArgumentParser) -> None:
    """Every option of every benchmark, on ``p`` (a scratch parser :func:`_add_bench` copies from)."""
    p.add_argument("--json", action="store_true", help="print JSON (always JSON; kept for scripts)")
    p.add_argument("--out", default=None, help="also write the JSON here")
    p.add_argument(
        "--duration",
        type=_positive,
        default=5.0,
        help="servo bench duration; load, rooms: the measurement window after warm-up [s] "
        "(default %(default)s)",
    )
    p.add_argument(
        "--rooms",
        type=int,
        default=8,
        help="rooms: rooms in all, a FEM room and ROOMS-1 balloon rooms, >= 2 (default "
        "%(default)s); the report gives per room the slowest user's patch rate",
    )
    _add_shared(p, "--servo-rate", help="servo bench rate [Hz]")
    p.add_argument(
        "--quick", action="store_true", help="fidelity: the documented subset (< 2 min, 2 cores)"
    )
    p.add_argument("--plot", default=None, metavar="DIR", help="fidelity: write the plots here")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="fidelity: recorded seed (default 0, deterministic); drawn: the draw's seed "
        "(default: a new one each run, printed)",
    )
    p.add_argument(
        "--conditions",
        type=int,
        default=24,
        help="drawn: conditions drawn from the declared set (default %(default)s)",
    )
    p.add_argument(
        "--hands",
        type=int,
        default=3,
        help="drawn: hands of the box per condition, the least damped stiffest corner "
        "among them (default %(default)s)",
    )
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
        "--design-reached",
        action="store_true",
        help=(
            "fidelity: also design every gain-table cell an object's reported K_o reaches (the "
            "stiffening object's), as a client has them once it has pressed there"
        ),
    )
    p.add_argument(
        "--design-margin",
        type=float,
        help=(
            "fidelity: the local models' designs hold on objects this fraction softer than the "
            "bottom of their cell (default: the product's, shared.gains.policy.DESIGN_MARGIN)"
        ),
    )
    p.add_argument(
        "--design-stiffer-by",
        type=float,
        help=(
            "fidelity: ... and this fraction stiffer than its top (default: the product's, "
            "shared.gains.policy.STIFFER_BY; narrower, what knowing the object that well would buy)"
        ),
    )
    p.add_argument(
        "--plane-check-s",
        type=float,
        default=0.0,
        help=(
            "fidelity: a verified plane renders this long after the own-response check first "
            "verifies its cell, as a client that checks it on arrival (default 0: checked ahead, "
            "in the background; the client's check takes about 2 s)"
        ),
    )
    p.add_argument(
        "--rest-hold-back-s",
        type=float,
        default=REST_HOLD_BACK_S,
        help=(
            "fidelity: after a verified plane in a contact the rest plane waits this long without "
            "one (default %(default)s s, the client's; 0: whenever no verified plane renders)"
        ),
    )
    p.add_argument(
        "--no-rest-plane",
        action="store_true",
        help=(
            "fidelity: the local models never render the rest plane (the client alone on the "
            "object does by default: shared.gains.rest_plane), as haptic client --no-rest-plane"
        ),
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


def _add_bench(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "bench",
        help="measure speed and fidelity (JSON), one subcommand a benchmark: " + ", ".join(BENCHES),
        description="Each benchmark is a subcommand with its own options: "
        "haptic bench NAME --help.",
    )
    benches = p.add_subparsers(dest="what", required=True, parser_class=type(p))
    scratch = argparse.ArgumentParser(add_help=False)
    _bench_options(scratch)
    every = {a.option_strings[0]: a for a in scratch._actions if a.option_strings}
    defaults = {a.dest: a.default for a in every.values()}
    for name, what in BENCHES.items():
        b = benches.add_parser(name, help=what, description=f"haptic bench {name}: {what}.")
        for flag in ("--json", "--out", *_BENCH_OPTIONS[name]):
            action = every[flag]
            default = _BENCH_DEFAULTS.get(name, {}).get(flag)
            if default is not None:  # this bench's own default: a copy of the option
                action = copy.copy(action)
                action.default = default
            b._add_action(action)
        mine = {every[f].dest for f in ("--json", "--out", *_BENCH_OPTIONS[name])}
        b.set_defaults(func=_cmd_bench, **{k: v for k, v in defaults.items() if k not in mine})


def _print_drawn_table(result: dict[str, object]) -> None:
    """A human-readable summary of ``haptic bench drawn`` (``--json`` for everything)."""
    summary = result["summary"]
    assert isinstance(summary, dict)
    print(f"seed {result['seed']}: {result['n']} conditions, {result['hands']} hands each")
    for name, row in summary.items():
        share = row["share"]
        pct = "-" if share is None else f"{share:.1%}"
        bad = ", ".join(str(i) for i in row["not_stable"]) or "none"
        print(f"{name:22s} box-stable {row['box_stable']:3d} of {row['of']:3d} ({pct}); not: {bad}")


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
