"""``haptic server --config FILE.toml``: every server option from a TOML file (stdlib tomllib).

A configuration file holds top-level keys named like the long options of ``haptic server`` with
``_`` for ``-`` (the argparse ``dest``): ``--sim-rate 50`` is ``sim_rate = 50.0``,
``--allow-origin URL`` (repeatable) is ``allow_origin = ["URL", ...]``, ``--insecure`` is
``insecure = true``. docs/server-config.example.toml lists them all.

Rooms (docs/usage.md): ``[rooms.NAME]`` tables name the rooms the server runs besides the
default one (its object, mesh, material, rate and caps: :data:`ROOM_OPTIONS`; a key not given is
the top-level one), and ``[room_templates.NAME]`` tables let a client make a room on demand by
joining ``/rooms/NAME/ws``: a name starting with the template's ``prefix`` is built from it, up
to ``max_rooms`` rooms in all. Their values reach ``haptic server`` as the defaults ``rooms``
and ``room_templates`` (``{name: {key: value}}``).

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
from haptic_collab.server.objects.fem import GRAVITY_MAX_M_S2
from haptic_collab.server.objects.shapes import STRESS_MESHES
from haptic_collab.server.solid_materials import SOLID_PRESETS
from haptic_collab.server.toml_file import read_toml
from haptic_collab.server.urls import valid_room_name


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


def _gravity(v: object) -> str | None:
    ok = isinstance(v, int | float) and 0.0 <= v <= GRAVITY_MAX_M_S2
    return None if ok else f"must be in [0, {GRAVITY_MAX_M_S2:g}] m/s^2"


def _one_of(*choices: str) -> Callable[[object], str | None]:
    def check(v: object) -> str | None:
        return None if v in choices else f"must be one of {', '.join(choices)}"

    return check


def _at_least_one(v: object) -> str | None:
    return None if isinstance(v, int) and v >= 1 else "must be >= 1"


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
    "mesh_repair": _Option(
        "bool", "make an open, non-manifold or several-body mesh one closed body (--mesh-repair)"
    ),
    "subdivisions": _Option("int", "icosphere subdivisions of the balloon", _subdivisions),
    "object": _Option("str", "object model", _one_of("balloon", "fem")),
    "inclusion": _Option(
        "list[str]",
        "closed surfaces inside the FEM solid (--inclusion, docs/palpation.md)",
        None,
        True,
    ),
    "inclusion_material": _Option(
        "list[str]", "the material of each inclusion, in order (--inclusion-material)"
    ),
    "material": _Option("str", "material preset or TOML file", _not_empty, True),
    "volume_cache": _Option("str", "folder of cached FEM volume meshes", _not_empty, True),
    "fem_volume_edge": _Option(
        "float",
        "with object fem: no tetrahedron larger than the regular one of edge this many pad radii",
        _positive,
    ),
    "gravity": _Option(
        "float", "the FEM solid sags under its own weight, g along -z [m/s^2]", _gravity
    ),
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
    "token_secret_file": _Option(
        "str", "file holding the secret room tokens are signed with", _not_empty, True
    ),
    "snapshot_dir": _Option("str", "folder of the rooms' snapshots", _not_empty, True),
    "drain_grace_s": _Option("float", "seconds from SIGTERM to exit at most", _positive),
    "max_rooms": _Option("int", "rooms this server runs at most", _at_least_one),
    "max_users": _Option(
        "int", "users each room admits at most unless its table says max_users", _at_least_one
    ),
    "room_processes": _Option("bool", "run each room's simulation in a process of its own"),
    "room_idle": _Option(
        "float", "seconds an empty on-demand room lives before it is closed", _positive
    ),
    "tick_priority": _Option(
        "str",
        "realtime: the simulation thread asks for SCHED_FIFO (or a negative nice) where allowed; "
        "off: the ordinary policy (docs/fem.md, 'Under load')",
        _one_of("realtime", "off"),
    ),
}

#: Keys of a ``[rooms.NAME]`` or ``[room_templates.NAME]`` table: what one room's object, rates
#: and caps are made of (anything not given is the top-level value of the same key).
ROOM_OPTIONS: dict[str, _Option] = {
    **{
        k: SERVER_OPTIONS[k]
        for k in (
            "object",
            "mesh",
            "mesh_scale",
            "mesh_size",
            "mesh_max_edge",
            "mesh_repair",
            "subdivisions",
            "material",
            "gravity",
            "sim_rate",
            "damping",
            "stiffness_scale",
            "primitive",
        )
    },
    "max_users": _Option("int", "haptic users in the room at once", _at_least_one),
    "max_viewers": _Option("int", "viewers in the room at once", _at_least_one),
}
#: Keys of a ``[room_templates.NAME]`` table besides :data:`ROOM_OPTIONS`.
TEMPLATE_OPTIONS: dict[str, _Option] = {
    **ROOM_OPTIONS,
    "prefix": _Option("str", "room names made from this template start with this ('': any name)"),
}
#: The tables a configuration file may hold: ``[rooms.NAME]`` and ``[room_templates.NAME]``.
ROOM_TABLES = {"rooms": ROOM_OPTIONS, "room_templates": TEMPLATE_OPTIONS}

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

    out: dict[str, object] = {}
    for key, value in data.items():
        if key in ROOM_TABLES:
            out[key] = _room_tables(where, key, value, p.parent)
            continue
        out[key] = _checked(where, key, value, SERVER_OPTIONS, p.parent)
    return out


def _checked(
    where: str, key: str, value: object, options: dict[str, _Option], folder: Path, table: str = ""
) -> object:
    """One key's value checked against ``options`` (converted, paths resolved)."""
    option = options.get(key)
    name = f"{table}{key}"
    if option is None:
        known = tuple(options) + (tuple(ROOM_TABLES) if not table else ())
        dashed = key.replace("-", "_").lstrip("_")
        if dashed in options:
            hint = f" (write {dashed!r}: option names with '_' for '-')"
        else:
            close = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"{where}: unknown key {name!r}{hint}; known keys: {', '.join(known)}")
    if not _type_ok(option.kind, value):
        raise ConfigError(
            f"{where}: {name} must be {_KIND_WORDS[option.kind]} ({option.doc}), got {value!r}"
        )
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{where}: {name} must be finite, got {value!r}")
    if option.check is not None:
        problem = option.check(value)
        if problem is not None:
            raise ConfigError(f"{where}: {name} {problem} ({option.doc}), got {value!r}")
    if option.kind == "float":
        value = float(value)  # type: ignore[arg-type]
    elif option.kind == "list[str]":
        value = list(value)  # type: ignore[call-overload]
    if option.path:
        if isinstance(value, list):
            value = [_resolve(key, str(v), folder) for v in value]
        else:
            value = _resolve(key, str(value), folder)
    return value


def _room_tables(where: str, key: str, value: object, folder: Path) -> dict[str, dict[str, object]]:
    """The ``[rooms.NAME]`` or ``[room_templates.NAME]`` tables, checked (:data:`ROOM_TABLES`)."""
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: {key} must be tables [{key}.NAME], got {value!r}")
    out: dict[str, dict[str, object]] = {}
    for name, table in value.items():
        if not valid_room_name(name):
            raise ConfigError(
                f"{where}: [{key}.{name}]: a name is 1-32 of a-z, 0-9 and -, starting and "
                "ending with a letter or digit"
            )
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: {key}.{name} must be a table [{key}.{name}]")
        out[name] = {
            k: _checked(where, k, v, ROOM_TABLES[key], folder, f"{key}.{name}.")
            for k, v in table.items()
        }
    prefixes = [str(t.get("prefix", "")) for t in out.values()] if key == "room_templates" else []
    if len(set(prefixes)) != len(prefixes):
        raise ConfigError(f"{where}: two [room_templates] have the same prefix")
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
    dests = {a.dest for a in parser._actions} | set(ROOM_TABLES)
    missing = [k for k in config if k not in dests]
    if missing:
        raise ConfigError(
            f"{path}: this 'haptic server' has no option for {', '.join(map(repr, missing))}"
        )
    parser.set_defaults(**config)
    return config
