"""What every ``haptic`` subcommand shares: the bad-input error, the parser and the option types.

:class:`CliError` is bad input (one line on stderr, exit status 2); :class:`_Parser` exits 2 with
one line too. The option types (``_finite``, ``_positive``, ...) check a value as argparse reads
it, and :data:`_SHARED` declares once the options that more than one subcommand takes
(:func:`_add_shared`). This module imports none of the command modules (they import it).
"""

from __future__ import annotations

import argparse
import math
from typing import Any, NoReturn

from haptic_collab.shared.extras import install_hint


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
        "given, the product's shared.gains.policy.STIFFER_BY (default: none)",
    },
    "--host": {"default": "127.0.0.1"},
    "--port": {"type": _nonneg_int, "default": 8765},
    "--mesh": {"default": "balloon"},
    "--mesh-scale": {"type": _positive, "default": None},
    "--mesh-size": {"type": _positive, "default": None},
    "--mesh-max-edge": {"type": _positive, "default": None, "metavar": "M"},
    "--material": {"default": None, "metavar": "NAME|FILE.toml"},
    "--object": {"choices": ["balloon", "fem"], "default": "balloon"},
    "--inclusion": {
        "action": "append",
        "default": [],
        "metavar": "FILE",
        "help": "with --object fem: a closed surface inside the solid (metres, the solid's frame) "
        "with a material of its own, e.g. a lump to palpate (repeat; docs/palpation.md)",
    },
    "--inclusion-material": {
        "action": "append",
        "default": [],
        "metavar": "NAME",
        "help": "the material of each --inclusion, in the same order: a solid preset, a TOML "
        "file, or PRESET*K (the preset K times as stiff, e.g. liver*10)",
    },
    "--subdivisions": {"type": _nonneg_int, "default": 4},
    "--latency-ms": {"type": _nonneg, "default": 0.0, "help": "injected one-way latency [ms]"},
    "--jitter-ms": {"type": _nonneg, "default": 0.0, "help": "injected jitter [ms]"},
    "--loss": {"type": _probability, "default": 0.0},
}


def _add_shared(p: argparse._ActionsContainer, flag: str, **more: Any) -> None:
    """Add the option ``flag`` of :data:`_SHARED` to ``p``; ``more`` (its help, a metavar) adds
    what the subcommand says of it (a TypeError if it tries to change what is shared)."""
    p.add_argument(flag, **_SHARED[flag], **more)


def _need_matplotlib() -> None:
    """Raise :class:`CliError` when the ``plots`` extra (matplotlib) is not installed."""
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        raise CliError(f"--plot needs matplotlib: {install_hint('plots')}")
