"""``haptic server --config FILE.toml``: every server option from a TOML file (stdlib tomllib).

A configuration file holds top-level keys named like the long options of ``haptic server`` with
``_`` for ``-`` (the argparse ``dest``): ``--sim-rate 50`` is ``sim_rate = 50.0``,
``--allow-origin URL`` (repeatable) is ``allow_origin = ["URL", ...]``, ``--insecure`` is
``insecure = true``. docs/server-config.example.toml lists them all.

:func:`load_server_config` reads and checks a file and returns ``{dest: value}``;
:func:`apply_server_config` hands that to the ``server`` subparser as defaults
(``parser.set_defaults``), so a flag given on the command line still wins over the file.

Paths in the file (``mesh`` when it is not ``balloon`` nor a stress shape's name, ``material``
when it is not a preset name, ``token_file``, ``tls_cert``, ``tls_key``) are relative to the file's folder, so a deployment can keep its
configuration, mesh and certificates together.

Nothing here starts a server, opens a socket or reads a clock.
"""

from __future__ import annotations

import argparse
import difflib
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from haptic_collab.server.materials import PRESETS
from haptic_collab.server.objects.shapes import STRESS_MESHES
from haptic_collab.server.solid_materials import SOLID_PRESETS
from haptic_collab.server.toml_file import read_toml


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message names the file and the key."""


@dataclass(frozen=True, slots=True)
class _Option:
    """One configuration key: its TOML type and a check of its value (None when it is fine)."""

    kind: str  # "str", "int", "float", "bool" or "list[str]"
    doc: str
    check: Callable[[object], str | None] | None = None
    path: bool = False  # resolved relative to the configuration file


def _positive(v: object) -> str | None:
    return None if isinstance(v, int | float) and v > 0 else "must be > 0"


def _nonneg(v: object) -> str | None:
    return None if isinstance(v, int | float) and v >= 0 else "must be >= 0"


def _probability(v: object) -> str | None:
    return None if isinstance(v, int | float) and 0.0 <= v < 1.0 else "must be in [0, 1)"


def _port(v: object) -> str | None:
    return None if isinstance(v, int) and 0 <= v <= 65535 else "must be in 0..65535"


def _subdivisions(v: object) -> str | None:
    return None if isinstance(v, int) and 0 <= v <= 7 else "must be in 0..7"


def _one_of(*choices: str) -> Callable[[object], str | None]:
    def check(v: object) -> str | None:
        return None if v in choices else f"must be one of {', '.join(choices)}"

    return check


def _not_empty(v: object) -> str | None:
    return None if isinstance(v, str) and v.strip() else "must not be empty"


#: Every key a server configuration file may hold (the ``dest`` of each ``haptic server``
#: option; ``material`` is ``--material NAME|FILE.toml``, :func:`server.materials.load_material`).
SERVER_OPTIONS: dict[str, _Option] = {
    "host": _Option("str", "address to listen on", _not_empty),
    "port": _Option("int", "TCP port (0: any free port)", _port),
    "mesh": _Option(
        "str",
        "'balloon', a stress shape (torus, box, plate, bowl, noisy-sphere, uneven) or a mesh "
        "file (STL, OBJ, PLY, OFF, GLB)",
        _not_empty,
        True,
    ),
    "mesh_scale": _Option("float", "multiply the file's coordinates by this", _positive),
    "mesh_size": _Option("float", "rescale so the largest extent is this [m]", _positive),
    "mesh_max_edge": _Option("float", "refine until no edge is longer than this [m]", _positive),
    "subdivisions": _Option("int", "icosphere subdivisions of the balloon", _subdivisions),
    "object": _Option("str", "object model", _one_of("balloon", "fem")),
    "material": _Option("str", "material preset or TOML file", _not_empty, True),
    "volume_cache": _Option("str", "folder of cached FEM volume meshes", _not_empty, True),
    "sim_rate": _Option("float", "simulation rate [Hz]", _positive),
    "damping": _Option("float", "object damping (visco-elastic, eq. 9) [Pa*s/m]", _nonneg),
    "stiffness_scale": _Option("float", "multiply every stiffness term by this", _positive),
    "primitive": _Option("str", "local model primitive", _one_of("plane", "sphere")),
    "latency_ms": _Option("float", "injected one-way latency [ms]", _nonneg),
    "jitter_ms": _Option("float", "injected jitter [ms]", _nonneg),
    "loss": _Option("float", "injected loss of state frames", _probability),
    "seed": _Option("int", "seed of the latency injection"),
    "duration": _Option("float", "stop after this many seconds", _positive),
    "token_file": _Option("str", "accepted tokens file", _not_empty, True),
    "token": _Option("str", "one accepted token, role user", _not_empty),
    "allow_origin": _Option("list[str]", "browser origins allowed besides the server's own"),
    "tls_cert": _Option("str", "TLS certificate (PEM)", _not_empty, True),
    "tls_key": _Option("str", "TLS key (PEM)", _not_empty, True),
    "insecure": _Option("bool", "listen off loopback without tokens"),
    "log_level": _Option("str", "log verbosity", _one_of("debug", "info", "warning", "error")),
    "agones_empty_shutdown": _Option(
        "float", "seconds empty before Agones Shutdown (0: never)", _nonneg
    ),
    "metrics_token_file": _Option(
        "str", "file holding the /metrics bearer token", _not_empty, True
    ),
}

#: Values of path keys that are names, not files (kept as they are); the stress shapes'
#: names (``mesh``) and the material presets (``material``) too, see :func:`_resolve`.
_NOT_PATHS = {"mesh": ("balloon",)}


def _type_ok(kind: str, value: object) -> bool:
    if kind == "bool":
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    if kind == "int":
        return isinstance(value, int)
    if kind == "float":
        return isinstance(value, int | float)
    if kind == "str":
        return isinstance(value, str)
    return isinstance(value, list) and all(isinstance(x, str) for x in value)


_KIND_WORDS = {
    "str": "a string",
    "int": "a whole number",
    "float": "a number",
    "bool": "true or false",
    "list[str]": "a list of strings",
}


def _resolve(key: str, value: str, folder: Path) -> str:
    """A path value made relative to the configuration file's folder (names kept)."""
    if value in _NOT_PATHS.get(key, ()):
        return value
    if key == "mesh" and value in STRESS_MESHES:
        return value
    if key == "material" and (value in PRESETS or value in SOLID_PRESETS):
        return value
    p = Path(value).expanduser()
    return str(p if p.is_absolute() else folder / p)


def load_server_config(path: str | Path) -> dict[str, object]:
    """Read a ``haptic server`` configuration file.

    Parameters
    ----------
    path : str or pathlib.Path
        A TOML file of top-level keys from :data:`SERVER_OPTIONS`.

    Returns
    -------
    dict
        ``{dest: value}`` for the keys the file sets: floats for float options (a TOML integer
        is accepted), ints, bools, strings, a list of strings for ``allow_origin``; path values
        resolved against the file's folder.

    Raises
    ------
    ConfigError
        The file is missing or unreadable, not valid TOML (line and column given), or has an
        unknown key (the closest known one is suggested; ``sim-rate`` for ``sim_rate`` too), a
        value of the wrong type, NaN/inf, or out of range. The message starts with the file and
        names the key.
    """
    p = Path(path)
    where = str(p)
    data = read_toml(p, "configuration", ConfigError)

    known = tuple(SERVER_OPTIONS)
    out: dict[str, object] = {}
    for key, value in data.items():
        option = SERVER_OPTIONS.get(key)
        if option is None:
            dashed = key.replace("-", "_").lstrip("_")
            if dashed in SERVER_OPTIONS:
                hint = f" (write {dashed!r}: option names with '_' for '-')"
            else:
                close = difflib.get_close_matches(key, known, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(f"{where}: unknown key {key!r}{hint}; known keys: {', '.join(known)}")
        if not _type_ok(option.kind, value):
            raise ConfigError(
                f"{where}: {key} must be {_KIND_WORDS[option.kind]} ({option.doc}), got {value!r}"
            )
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{where}: {key} must be finite, got {value!r}")
        if option.check is not None:
            problem = option.check(value)
            if problem is not None:
                raise ConfigError(f"{where}: {key} {problem} ({option.doc}), got {value!r}")
        if option.kind == "float":
            value = float(value)  # type: ignore[arg-type]
        elif option.kind == "list[str]":
            value = list(value)  # type: ignore[call-overload]
        if option.path:
            value = _resolve(key, str(value), p.parent)
        out[key] = value
    return out


def apply_server_config(parser: argparse.ArgumentParser, path: str | Path) -> dict[str, object]:
    """Make a configuration file's values the defaults of the ``haptic server`` parser.

    ``parser.set_defaults(**load_server_config(path))``: parse the command line again after
    this and every flag given explicitly overrides the file. ``allow_origin`` is an ``append``
    option: origins given with ``--allow-origin`` are added to the file's list. A ``log_level``
    in the file beats a ``--log-level`` given *before* ``server`` (argparse copies a subparser's
    defaults over the top-level values); one given after ``server`` wins.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The ``server`` subparser (every key of the file must be one of its ``dest``).
    path : str or pathlib.Path

    Returns
    -------
    dict
        The values applied.

    Raises
    ------
    ConfigError
        As :func:`load_server_config`, or a key this parser has no option for (e.g.
        ``material`` before ``--material`` exists).
    """
    config = load_server_config(path)
    dests = {a.dest for a in parser._actions}
    missing = [k for k in config if k not in dests]
    if missing:
        raise ConfigError(
            f"{path}: this 'haptic server' has no option for {', '.join(map(repr, missing))}"
        )
    parser.set_defaults(**config)
    return config
