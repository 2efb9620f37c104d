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
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn


class CliError(Exception):
    """Bad input: printed as one line on stderr, exit status 2."""


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


def _probability(text: str) -> float:
    value = _finite(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {text!r}")
    return value


# ---------------------------------------------------------------------------------------- stability
def _cmd_stability(args: argparse.Namespace) -> int:
    from shared.stability import analyze

    try:
        res = analyze(
            args.k_o,
            args.k_h,
            i_gain=args.i_gain,
            damping=args.damping,
            servo_rate_hz=args.servo_rate,
            sim_rate_hz=args.sim_rate,
            delay_ticks=args.delay_ticks,
        )
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if args.json:
        print(json.dumps(res.to_json()))
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
    return 0


def _add_stability(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "stability",
        help="stability of the simulation loop for given K_o, K_h, I (paper eq. 8, 10, 15, 16)",
        description="Verdict on the slow-rate simulation loop z^-(1+D) L_h(z) D(z) (Fig. 6).",
    )
    p.add_argument("--k-o", type=_positive, required=True, help="object stiffness K_o [N/m]")
    p.add_argument("--k-h", type=_positive, required=True, help="local model stiffness K_h [N/m]")
    p.add_argument("--i-gain", type=_nonneg, default=0.0, help="integral weight I [N/(m*s)]; 0 = P")
    p.add_argument("--damping", type=_nonneg, default=0.0, help="object damping b [N*s/m]")
    p.add_argument("--servo-rate", type=_positive, default=1000.0, help="servo rate 1/T [Hz]")
    p.add_argument("--sim-rate", type=_positive, default=20.0, help="simulation rate [Hz]")
    p.add_argument(
        "--delay-ticks", type=_nonneg_int, default=0, help="extra simulation ticks of delay"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_stability)


# ---------------------------------------------------------------------------------------- reproduce
def _cmd_reproduce(args: argparse.Namespace) -> int:
    from shared.reproduce import reproduce

    results = reproduce(args.figure, Path(args.out))
    for name in results:
        print(f"wrote {Path(args.out) / (name + '.png')} and {name}.json")
    return 0


def _add_reproduce(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("reproduce", help="reproduce the paper's Fig. 7, 8 and 9 (PNG + JSON)")
    p.add_argument("figure", choices=["fig7", "fig8", "fig9", "all"])
    p.add_argument("--out", default="out/figures", help="output directory")
    p.set_defaults(func=_cmd_reproduce)


# -------------------------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    """The ``haptic`` argument parser with every subcommand."""
    parser = _Parser(
        prog="haptic", description="Multirate haptic collaboration on a shared deformable object."
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_stability(sub)
    _add_reproduce(sub)
    for extra in _EXTRA:
        extra(sub)
    return parser


_EXTRA: list = []  # subcommands registered by later sections of this module


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``haptic`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"haptic {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
