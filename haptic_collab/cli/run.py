"""The subcommands that run the system: ``haptic server``, ``lobby``, ``client``, ``demo``, ``devices``.

Each command's handler (``_cmd_*``) and parser (``_add_*``), the options they share (the object and
its mesh, the stiffness scale, the simulated hand), and the logging of the commands that log
(``--log-level``). The server, the client and the demo are imported when their command runs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from haptic_collab.cli.args import (
    CliError,
    _add_shared,
    _finite,
    _need_matplotlib,
    _nonneg,
    _nonneg_int,
    _positive,
    _whole_positive,
    _why,
)

# ----------------------------------------------------------------------------------- object options
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


#: ``--gravity`` without a value [m/s^2]: standard gravity, rounded.
STANDARD_GRAVITY_M_S2 = 9.81
#: ``--gravity`` at most [m/s^2] (:data:`server.objects.fem.GRAVITY_MAX_M_S2`, not imported here:
#: it loads scipy and trimesh; a test checks they agree).
GRAVITY_MAX_M_S2 = 100.0


def _gravity(text: str) -> float:
    """``--gravity G``: a finite number in [0, :data:`GRAVITY_MAX_M_S2`] m/s^2."""
    value = _nonneg(text)
    if value > GRAVITY_MAX_M_S2:
        raise argparse.ArgumentTypeError(
            f"must be at most {GRAVITY_MAX_M_S2:g} m/s^2 (9.81 on Earth), got {text!r}"
        )
    return value


def _add_gravity(p: argparse.ArgumentParser, help: str) -> None:
    """``--gravity [G]`` on ``p`` (the server's and the demo's, each with its own ``help``):
    :func:`_gravity`, :data:`STANDARD_GRAVITY_M_S2` without a value, 0 (no weight) without it."""
    p.add_argument(
        "--gravity",
        type=_gravity,
        nargs="?",
        const=STANDARD_GRAVITY_M_S2,
        default=0.0,
        metavar="G",
        help=help,
    )


# ------------------------------------------------------------------------------------------ logging
#: ``--log-level`` choices (Python logging levels).
LOG_LEVELS = ("debug", "info", "warning", "error")
#: Subcommands that log (and take ``--log-level`` after their name as well as before).
_LOGGING_COMMANDS = ("server", "lobby", "client", "demo")


def _configure_logging(args: argparse.Namespace) -> None:
    """Log to stderr at ``--log-level`` (default info) with time, logger name and level.

    The websockets library's own lines (every HTTP response, connection opened and closed) only
    at debug: the server and the client say what happened to a connection themselves, with its
    user, and at info those lines buried them (a server log was mostly "HTTP response sent")."""
    import logging

    level = getattr(logging, str(getattr(args, "log_level", "info")).upper(), logging.INFO)
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger().setLevel(level)
    logging.getLogger("websockets").setLevel(level if level <= logging.DEBUG else logging.WARNING)


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


def _inclusion_args(
    args: argparse.Namespace, fem: bool | None = None
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``--inclusion`` files and ``--inclusion-material`` names, checked as a pair (``fem``:
    whether the object is the FEM solid; default ``--object fem``).

    Raises
    ------
    CliError
        Not one material per file, or inclusions without ``--object fem``.
    """
    files = tuple(getattr(args, "inclusion", None) or ())
    materials = tuple(getattr(args, "inclusion_material", None) or ())
    if len(files) != len(materials):
        raise CliError(
            f"{len(files)} --inclusion file(s) but {len(materials)} --inclusion-material(s): "
            "give one material per inclusion, in the same order"
        )
    if files and not (args.object == "fem" if fem is None else fem):
        raise CliError("--inclusion needs --object fem (an inclusion is a region of the solid)")
    return files, materials


def _server_options(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """The :class:`server.main.ServerOptions` of parsed ``haptic server`` arguments.

    Raises
    ------
    CliError
        As :func:`_inclusion_args`.
    """
    from haptic_collab.server.main import ServerOptions

    files, materials = _inclusion_args(args)
    return ServerOptions(
        mesh_repair=bool(getattr(args, "mesh_repair", False)),
        inclusions=files,
        inclusion_materials=materials,
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
        fem_volume_edge_pads=args.fem_volume_edge,
        agones_empty_shutdown_s=args.agones_empty_shutdown,
        metrics_token_file=args.metrics_token_file,
        rooms=dict(args.rooms or {}),
        room_templates=dict(args.room_templates or {}),
        max_rooms=args.max_rooms,
        max_users=getattr(args, "max_users", None),
        room_idle_s=args.room_idle,
        token_secret_file=args.token_secret_file,
        snapshot_dir=args.snapshot_dir,
        drain_grace_s=args.drain_grace_s,
        room_processes=args.room_processes,
        gravity_m_s2=float(getattr(args, "gravity", 0.0) or 0.0),
        tick_priority=getattr(args, "tick_priority", "realtime"),
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
    _add_shared(
        p,
        "--host",
        help="address to listen on (default %(default)s: this machine only; another address "
        "needs tokens, docs/security.md)",
    )
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
    p.add_argument(
        "--fem-volume-edge",
        type=_positive,
        default=None,
        metavar="PADS",
        help="with --object fem: no tetrahedron larger than the regular one of edge PADS finger-pad "
        "radii (a volume size limit tied to the pad; default 2.5; 1 brings the default sphere's "
        "K_o 2.9 %% nearer a converged one at 18 times the factor's size; docs/fem.md)",
    )
    _add_gravity(
        p,
        "with --object fem: the solid sags under its own weight at start, G [m/s^2] along "
        f"-z of the object's frame (G in [0, {GRAVITY_MAX_M_S2:g}]; {STANDARD_GRAVITY_M_S2:g} "
        "when given without a value; default 0: no weight; docs/fem.md)",
    )
    _add_shared(p, "--mesh-scale", help="multiply the file's coordinates by S")
    _add_shared(p, "--mesh-size", help="rescale so the largest extent is this [m]")
    _add_shared(p, "--mesh-max-edge", help=_MESH_MAX_EDGE_HELP)
    p.add_argument(
        "--mesh-repair",
        action="store_true",
        help="make an open, non-manifold or several-body mesh one closed body and say what "
        "changed (docs/real-objects.md); without it such a mesh is refused",
    )
    _add_shared(p, "--inclusion")
    _add_shared(p, "--inclusion-material")
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
    sec.add_argument(
        "--metrics-token-file",
        default=None,
        metavar="FILE",
        help="token a /metrics scrape must carry (Authorization: Bearer); without it only a "
        "server on loopback serves /metrics",
    )
    sec.add_argument(
        "--token-secret-file",
        default=None,
        metavar="FILE",
        help="secret that room tokens are signed with (haptic token); a room token admits to "
        "one room in one role until it expires",
    )
    rooms = p.add_argument_group("rooms ([rooms.NAME] and [room_templates.NAME] in --config)")
    rooms.add_argument(
        "--max-rooms",
        type=_at_least_one,
        default=16,
        metavar="N",
        help="rooms this server runs at most, the default one included (default %(default)s)",
    )
    rooms.add_argument(
        "--max-users",
        type=_at_least_one,
        default=None,
        metavar="N",
        help="users each room admits at most unless its [rooms]/[room_templates] table says "
        "max_users (default 32); the server admits at most --max-rooms times this",
    )
    rooms.add_argument(
        "--room-processes",
        action="store_true",
        help="run each room's simulation in a process of its own (a slow room's tick then "
        "delays no other room; a room process that dies is restarted)",
    )
    rooms.add_argument(
        "--tick-priority",
        choices=["realtime", "off"],
        default=os.environ.get("HAPTIC_TICK_PRIORITY", "realtime"),
        help="realtime: the simulation thread asks for SCHED_FIFO 5, else nice -10, where "
        "allowed (default, or $HAPTIC_TICK_PRIORITY); off: the ordinary policy (docs/fem.md, "
        "'Under load')",
    )
    rooms.add_argument(
        "--room-idle",
        type=_positive,
        default=300.0,
        metavar="S",
        help="close a room made on demand after S seconds without a connection "
        "(default %(default)s)",
    )
    p.add_argument(
        "--snapshot-dir",
        default=None,
        metavar="DIR",
        help="on SIGTERM save each room's object state here; a room made again resumes it",
    )
    p.add_argument(
        "--drain-grace-s",
        type=_positive,
        default=10.0,
        metavar="S",
        help="on SIGTERM: tell clients server_draining, close 1012, exit within S s "
        "(default %(default)s)",
    )
    p.add_argument(
        "--agones-empty-shutdown",
        type=float,
        default=300.0,
        metavar="S",
        help="under Agones (AGONES_SDK_HTTP_PORT set): ask for Shutdown after S seconds empty "
        "(0: never; default %(default)s)",
    )
    p.set_defaults(func=_cmd_server, rooms={}, room_templates={})


def _at_least_one(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _cmd_token(args: argparse.Namespace) -> int:
    """``haptic token``: print a room token signed with the server's secret."""
    import time

    from haptic_collab.server.security import MAX_TOKEN_TTL_S, load_secret, make_room_token

    if not 0.0 < args.ttl <= MAX_TOKEN_TTL_S:
        raise CliError(f"--ttl must be in (0, {MAX_TOKEN_TTL_S:g}] s, got {args.ttl:g}")
    try:
        secret = load_secret(args.secret_file)
        token = make_room_token(secret, args.room, args.role, time.time() + args.ttl)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    print(token)
    return 0


def _add_token(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "token",
        help="print a signed, expiring token for one room and one role (docs/security.md)",
    )
    p.add_argument("--room", required=True, help="the room's name (the room at /rooms/NAME/ws)")
    p.add_argument(
        "--role",
        choices=["user", "viewer"],
        default="user",
        help="user: push and watch; viewer: watch (default %(default)s)",
    )
    p.add_argument(
        "--ttl",
        type=_positive,
        default=3600.0,
        metavar="S",
        help="valid for S seconds from now (default %(default)g, at most 30 days)",
    )
    p.add_argument(
        "--secret-file",
        required=True,
        metavar="FILE",
        help="the server's --token-secret-file",
    )
    p.set_defaults(func=_cmd_token)


# -------------------------------------------------------------------------------------------- lobby
def _room_server_option(text: str):  # type: ignore[no-untyped-def]
    from haptic_collab.server.lobby import RoomServer

    try:
        return RoomServer.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _tls_server_context(cert: str | None, key: str | None):  # type: ignore[no-untyped-def]
    """An SSL context serving ``cert`` and ``key`` (None without them); CliError when bad."""
    import ssl

    if cert is None and key is None:
        return None
    if cert is None or key is None:
        raise CliError("--tls-cert and --tls-key go together")
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise CliError(f"cannot use the TLS certificate {cert}: {exc}") from None
    return ctx


def _lobby_backend(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """The lobby's back end of parsed ``haptic lobby`` arguments (exactly one is given)."""
    import ssl

    from haptic_collab.server.lobby import AgonesAllocator, LocalServers, load_servers

    servers = list(args.server)
    if args.servers_file:
        try:
            servers += load_servers(args.servers_file)
        except ValueError as exc:
            raise CliError(str(exc)) from None
    if bool(servers) == bool(args.agones_allocator):
        raise CliError(
            "give the room servers (--server URL, --servers-file FILE) or --agones-allocator URL, "
            "one of the two"
        )
    if args.status_token_file and not servers:
        raise CliError(
            "--status-token-file is for the local room servers (--server): the Agones back end "
            "does not read /status"
        )
    if servers:
        status_token = None
        if args.status_token_file:
            from haptic_collab.server.lobby_backends import load_status_token

            try:
                status_token = load_status_token(args.status_token_file)
            except ValueError as exc:
                raise CliError(str(exc)) from None
        return LocalServers(servers, status_token=status_token)
    context = None
    if args.agones_allocator.startswith("https://"):
        try:
            context = ssl.create_default_context(cafile=args.agones_ca)
            if args.agones_client_cert:
                context.load_cert_chain(args.agones_client_cert, args.agones_client_key)
        except (OSError, ssl.SSLError) as exc:
            raise CliError(f"cannot use the allocator's TLS files: {exc}") from None
    labels = {"agones.dev/fleet": args.agones_fleet} if args.agones_fleet else {}
    try:
        return AgonesAllocator(
            args.agones_allocator,
            namespace=args.agones_namespace,
            match_labels=labels,
            port_name=args.agones_port_name,
            scheme=args.public_scheme,
            context=context,
        )
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _cmd_lobby(args: argparse.Namespace) -> int:
    """``haptic lobby``: serve room names to servers and room tokens until SIGINT or SIGTERM."""
    import asyncio
    import signal

    from haptic_collab.server.lobby import Lobby
    from haptic_collab.server.lobby_peers import Peers
    from haptic_collab.server.main import ServerOptions, build_metrics_token
    from haptic_collab.server.security import TokenTable, load_secret

    _configure_logging(args)
    backend = _lobby_backend(args)
    try:
        secret = load_secret(args.token_secret_file)
        auth = TokenTable.load(args.token_file) if args.token_file else None
        metrics = build_metrics_token(ServerOptions(metrics_token_file=args.metrics_token_file))
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if bool(args.peer) != bool(args.peer_self):
        raise CliError("--peer URL (every replica) and --peer-self URL (this one) go together")
    try:
        peers = Peers.of(args.peer, args.peer_self) if args.peer else None
        lobby = Lobby(
            backend,
            secret,
            host=args.host,
            port=args.port,
            token_ttl_s=args.token_ttl,
            auth=auth,
            insecure=args.insecure,
            ssl_context=_tls_server_context(args.tls_cert, args.tls_key),
            trusted_proxies=args.trusted_proxy,
            max_connections_per_address=args.max_connections_per_address,
            peers=peers,
            metrics_token=metrics,
        )
    except ValueError as exc:
        raise CliError(str(exc)) from None

    async def serve() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        if args.duration is not None:
            loop.call_later(args.duration, stop.set)
        await lobby.serve_forever(stop)

    try:
        asyncio.run(serve())
    except OSError as exc:
        raise CliError(f"cannot listen on {args.host}:{args.port}: {exc.strerror or exc}") from None
    return 0


def _add_lobby(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "lobby",
        help="find a room: map a room name to a server's websocket URL and a room token "
        "(docs/deploy.md#finding-a-room)",
    )
    _add_shared(
        p,
        "--host",
        help="address to listen on (default %(default)s; another address needs --token-file)",
    )
    p.add_argument(
        "--port", type=_nonneg_int, default=8780, help="TCP port (0: any; default %(default)s)"
    )
    local = p.add_argument_group("local room servers")
    local.add_argument(
        "--server",
        type=_room_server_option,
        action="append",
        default=[],
        metavar="URL[=PUBLIC]",
        help="a room server the lobby reads /status of, e.g. http://127.0.0.1:8765; "
        "=ws://HOST:PORT when clients reach it elsewhere (repeat)",
    )
    local.add_argument(
        "--servers-file",
        default=None,
        metavar="FILE.toml",
        help="room servers as [[servers]] tables with url (and public)",
    )
    local.add_argument(
        "--status-token-file",
        default=None,
        metavar="FILE",
        help="the room servers' metrics token (their --metrics-token-file), sent as Bearer with "
        "each /status request: servers off loopback answer /status only with it",
    )
    ag = p.add_argument_group("Agones (a GameServerAllocation per room name)")
    ag.add_argument(
        "--agones-allocator",
        default=None,
        metavar="URL",
        help="the allocator service, https://HOST:PORT (POST /gameserverallocation)",
    )
    ag.add_argument("--agones-namespace", default="default", help="the fleet's namespace")
    ag.add_argument(
        "--agones-fleet",
        default=None,
        metavar="NAME",
        help="allocate only from this fleet (label agones.dev/fleet)",
    )
    ag.add_argument(
        "--agones-port-name",
        default=None,
        metavar="NAME",
        help="the GameServer port clients use (default: its first)",
    )
    ag.add_argument("--agones-ca", default=None, metavar="PEM", help="the allocator's CA")
    ag.add_argument(
        "--agones-client-cert", default=None, metavar="PEM", help="client certificate (mTLS)"
    )
    ag.add_argument("--agones-client-key", default=None, metavar="PEM", help="its key")
    ag.add_argument(
        "--public-scheme",
        choices=["ws", "wss"],
        default="ws",
        help="what clients speak to the allocated servers: wss when the game port serves TLS "
        "(deploy/agones/fleet.yaml does; default %(default)s)",
    )
    sec = p.add_argument_group("tokens (docs/security.md)")
    sec.add_argument(
        "--token-secret-file",
        required=True,
        metavar="FILE",
        help="the room servers' --token-secret-file: the lobby signs room tokens with it",
    )
    sec.add_argument(
        "--token-ttl",
        type=_positive,
        default=600.0,
        metavar="S",
        help="room tokens expire S seconds after the lobby signs them (default %(default)g)",
    )
    sec.add_argument(
        "--token-file",
        default=None,
        metavar="FILE",
        help="tokens a request must carry (Authorization: Bearer; TOKEN ROLE [NAME] lines; a "
        "viewer's token gets only viewer tokens)",
    )
    sec.add_argument(
        "--insecure",
        action="store_true",
        help="listen off loopback without --token-file (anyone who reaches it gets tokens)",
    )
    sec.add_argument("--tls-cert", default=None, metavar="PEM", help="serve https")
    sec.add_argument("--tls-key", default=None, metavar="PEM", help="the certificate's key")
    sec.add_argument(
        "--metrics-token-file",
        default=None,
        metavar="FILE",
        help="the token a scrape of /metrics must carry (Bearer); without it /metrics is served "
        "on loopback only",
    )
    lim = p.add_argument_group("limits and replicas (docs/deploy.md#finding-a-room)")
    lim.add_argument(
        "--trusted-proxy",
        action="append",
        default=[],
        metavar="ADDRESS|NETWORK",
        help="a proxy whose X-Forwarded-For names the client (e.g. 10.0.0.0/8; repeat); from "
        "anyone else the header is ignored",
    )
    lim.add_argument(
        "--max-connections-per-address",
        type=_whole_positive,
        default=16,
        metavar="N",
        help="connections one address may hold open at once (default %(default)s)",
    )
    lim.add_argument(
        "--peer",
        action="append",
        default=[],
        metavar="URL",
        help="every lobby replica, http(s)://HOST:PORT, the same list on each (repeat): each "
        "room name is placed by one owner replica",
    )
    lim.add_argument(
        "--peer-self", default=None, metavar="URL", help="this replica's entry of --peer"
    )
    p.add_argument("--duration", type=_positive, default=None, help="stop after this many seconds")
    p.set_defaults(func=_cmd_lobby)


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


#: ``haptic client --url`` when neither it nor ``--lobby`` is given.
_DEFAULT_URL = "ws://127.0.0.1:8765/ws"


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
    """``--hand-*`` values as :data:`client.devices.sim_backend.HAND_OPTIONS` keys (only those given)."""
    given = {
        "hand_mass_kg": args.hand_mass,
        "hand_stiffness_n_per_m": args.hand_stiffness,
        "hand_damping_n_s_per_m": args.hand_damping,
    }
    return {k: v for k, v in given.items() if v is not None}


def _client_options(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """The :class:`client.app.ClientOptions` of parsed ``haptic client`` arguments.

    The ``--hand-*`` flags travel in the trajectory options (the simulated hand pulls the device
    along the trajectory); :func:`client.devices.opener.make_device` takes them out into the hand.
    """
    from haptic_collab.client.app import ClientOptions
    from haptic_collab.client.gain_build import gain_build_default

    if args.lobby is not None and args.url is not None:
        raise CliError("--lobby finds the room's server: give it or --url, not both")
    if (args.lobby is None) != (args.room is None):
        raise CliError("--lobby URL and --room NAME go together")
    return ClientOptions(
        url=args.url or _DEFAULT_URL,
        lobby=args.lobby,
        room=args.room,
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
        lobby_token=args.lobby_token,
        ca_file=args.ca_file,
        gains=args.gains,
        rest_plane=not args.no_rest_plane,
        gain_cache=not args.no_gain_cache,
        gain_build=(gain_build_default() if args.gain_build is None else args.gain_build)
        and not args.no_gain_cache,
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
    p.add_argument(
        "--url",
        default=None,
        help=f"the server's websocket URL, as `haptic server` prints it (default {_DEFAULT_URL}; "
        "a room: ws://HOST:PORT/rooms/NAME/ws)",
    )
    p.add_argument(
        "--lobby",
        default=None,
        metavar="URL",
        help="ask this lobby (haptic lobby, http://HOST:PORT) where --room runs and for a room "
        "token, instead of --url; asked again when the server drains",
    )
    p.add_argument("--room", default=None, metavar="NAME", help="the room to ask the lobby for")
    p.add_argument("--name", default="A", help="user name shown to others")
    p.add_argument(
        "--device",
        default="sim:press",
        help="the force-feedback device: sim:press | sim:rest | sim:replay:FILE (simulated), "
        "hid:VID:PID, openhaptics[:NAME], forcedimension[:ID], haply[:PORT], or a plug-in's; "
        "`haptic devices` lists what is here (default %(default)s; docs/devices.md)",
    )
    _add_shared(p, "--profile", help="simulated device profile (see haptic devices)")
    p.add_argument(
        "--hid-profile", default=None, help="generic HID device profile (name or JSON file)"
    )
    _add_shared(
        p,
        "--local-model",
        help="the local model: p (a spring K_h) or pi (K_h and an integral I, the paper's "
        "proportional-integral virtual coupling; default %(default)s)",
    )
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
        "--no-rest-plane",
        action="store_true",
        help="alone on the object, render the simulation's surface with the designed gains "
        "instead of the object's rest plane with its stiffness (shared.gains.rest_plane)",
    )
    p.add_argument(
        "--no-gain-cache",
        action="store_true",
        help="neither read nor write this machine's cache of gain designs "
        "($HAPTIC_GAIN_CACHE, else ~/.cache/haptic-collab; the shipped tables still load); "
        "implies --no-gain-build",
    )
    p.add_argument(
        "--no-gain-build",
        dest="gain_build",
        action="store_false",
        default=None,  # the client's default: build, unless $HAPTIC_GAIN_BUILD=0
        help="do not build the gain table of a device that has none (no shipped table, not in "
        "the cache) before joining (minutes once, with a progress bar, then cached): its cells "
        "are designed during contact and feel different until ready (default: build, unless "
        "$HAPTIC_GAIN_BUILD=0)",
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
        help="time-domain passivity controller at the device port; auto = on for either local "
        "model (default %(default)s)",
    )
    _add_shared(p, "--margin", help="K_o margin of the gain design (default %(default)s)")
    p.add_argument(
        "--token",
        default=None,
        help="the server's token (default: $HAPTIC_TOKEN; prefer the variable: it stays out of ps)",
    )
    p.add_argument(
        "--lobby-token",
        default=None,
        help="the lobby's token, when it asks for one (default: $HAPTIC_LOBBY_TOKEN)",
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
    from haptic_collab.client.devices.opener import list_devices

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


# --------------------------------------------------------------------------------------------- demo
def _cmd_demo(args: argparse.Namespace) -> int:
    from haptic_collab.demo import DemoOptions, DemoVerdictError, default_duration, run_demo

    if args.plot:
        _need_matplotlib()  # before the run, not after it

    # the palpation scenario's object is the FEM solid whatever --object says
    files, materials = _inclusion_args(args, fem=args.object == "fem" or args.scenario != "press")
    opts = DemoOptions(
        scenario=args.scenario,
        inclusions=files,
        inclusion_materials=materials,
        duration_s=args.duration if args.duration is not None else default_duration(args.scenario),
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
        gravity_m_s2=float(args.gravity),
    )
    if opts.gravity_m_s2 > 0.0 and args.object != "fem" and args.scenario == "press":
        # before anything starts, as the server would refuse it
        raise CliError(
            "--gravity needs --object fem or --scenario palpation (the balloon has no weight model)"
        )
    try:
        run_demo(opts)
    except ValueError as exc:
        raise CliError(_why(exc)) from None
    except DemoVerdictError as exc:  # the report is written; the verdict is the exit status
        return exc.exit_code
    except RuntimeError as exc:
        print(f"haptic demo: failed: {exc}", file=sys.stderr)
        return 1
    return 0


def _add_demo(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "demo", help="server + two simulated users on one shared balloon, and a viewer: start here"
    )
    p.add_argument(
        "--duration",
        type=_positive,
        default=None,
        help="run length [s] (>= 12; default 20, or 30 for --scenario palpation: its slide is "
        "slow enough to feel the lump)",
    )
    p.add_argument(
        "--scenario",
        choices=["press", "palpation"],
        default="press",
        help="press: A presses the top and holds, B rests on the side (default); palpation: "
        "the FEM liver with a stiff lump under the top, A presses in and sweeps across it and "
        "back, B rests on the side and feels the sweep (docs/palpation.md)",
    )
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
    _add_shared(p, "--inclusion")
    _add_shared(p, "--inclusion-material")
    _add_gravity(
        p,
        "with --object fem or --scenario palpation: the solid sags under its own weight "
        f"at start, G [m/s^2] along -z (G in [0, {GRAVITY_MAX_M_S2:g}]; "
        f"{STANDARD_GRAVITY_M_S2:g} when given without a value; default 0: no weight); the "
        "users work on the sagged surface (docs/fem.md)",
    )
    _add_shared(p, "--port", help="server port (0: any free port)")
    _add_shared(
        p,
        "--host",
        help="server address (0.0.0.0: every interface; the viewer URLs of this machine are "
        "printed; default %(default)s)",
    )
    _add_shared(
        p,
        "--local-model",
        help="the local model: p (a spring K_h) or pi (K_h and an integral I, the paper's "
        "proportional-integral virtual coupling; default %(default)s)",
    )
    p.add_argument("--workdir", default=None, help="keep logs and telemetry here")
    _add_stiffness_scale(p)
    _add_hand(p)
    p.set_defaults(func=_cmd_demo)
