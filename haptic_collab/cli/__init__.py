"""The ``haptic`` command line: one console script, one subcommand per capability.

Subcommands import their implementation lazily so that ``haptic stability`` does not pay for the
server's or the client's imports. SI units everywhere: m, N, s; stiffness N/m.

Exit status: 0 on success (whatever a stability verdict says), 2 on bad input with one clear line on
stderr (no traceback), 1 on a runtime failure.

The parser and :func:`main` are here; the subcommands live in modules by group: :mod:`.args` (what
they share: option types, shared options, :class:`~.args.CliError`), :mod:`.design` (stability,
gains, gains-table), :mod:`.run` (server, client, demo, devices, logging) and :mod:`.research`
(reproduce, plot, protocol, bench).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from haptic_collab.cli import blas_threads  # noqa: F401  (first: before numpy is imported)
from haptic_collab.cli.args import CliError, _Parser
from haptic_collab.cli.design import _add_gains, _add_gains_table, _add_stability
from haptic_collab.cli.research import _add_bench, _add_plot, _add_protocol, _add_reproduce
from haptic_collab.cli.run import (
    _LOGGING_COMMANDS,
    _add_client,
    _add_demo,
    _add_devices,
    _add_lobby,
    _add_log_level,
    _add_server,
    _add_token,
    _configure_logging,
)
from haptic_collab.shared.extras import install_hint

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The ``haptic`` argument parser with every subcommand."""
    parser = _Parser(
        prog="haptic",
        description="Multirate haptic collaboration on a shared deformable object. Start with "
        "`haptic demo`: a server and two simulated users on this machine, and a viewer to open "
        "in a browser.",
    )
    _add_log_level(parser, top=True)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    # what a user runs first, then the design and research tools
    for add in (*_EXTRA, _add_stability, _add_gains, _add_gains_table, _add_reproduce):
        add(sub)
    for name in _LOGGING_COMMANDS:
        if name in sub.choices:
            _add_log_level(sub.choices[name], top=False)
    return parser


_EXTRA = [
    _add_demo,
    _add_server,
    _add_client,
    _add_lobby,
    _add_devices,
    _add_token,
    _add_plot,
    _add_protocol,
    _add_bench,
]


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
            f"haptic {args.command}: error: the figures need matplotlib: {install_hint('plots')}",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        return 130
