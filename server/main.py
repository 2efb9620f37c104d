"""``haptic server``: build the objects and the rooms, serve them over websockets.

The default room is built from the top-level options; each ``[rooms.NAME]`` of the configuration
(``ServerOptions.rooms``) is a room of its own built from the same options with that table's
keys on top (:func:`build_room`), and ``[room_templates.NAME]`` make rooms on demand
(:class:`RoomTemplates`).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import os
import signal
import ssl
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from haptic_collab.server.admission import RoomLimits
from haptic_collab.server.agones import (
    EMPTY_SHUTDOWN_S,
    AgonesAgent,
    AgonesOptions,
    AgonesSDK,
    start_agones,
)
from haptic_collab.server.app import DRAIN_GRACE_S, MAX_ROOMS, ROOM_IDLE_S, ServerApp
from haptic_collab.server.room import Room
from haptic_collab.server.room_process import RoomProxy, RoomSpec
from haptic_collab.server.security import (
    RoomTokens,
    TokenTable,
    is_loopback,
    load_secret,
    normalize_origin,
)
from haptic_collab.server.snapshots import check_directory
from haptic_collab.server.urls import DEFAULT_ROOM, room_page_path, valid_room_name, viewer_urls
from haptic_collab.shared.protocol import PROTOCOL_VERSION, LinkConditions
from haptic_collab.shared.rates import Rates, dividing_rates

#: The clients' servo rate the simulation rate must divide [Hz] (``haptic client``'s default).
CLIENT_SERVO_RATE_HZ = 1000.0

log = logging.getLogger("haptic.server")


@dataclass
class ServerOptions:
    """Options of ``haptic server`` (SI units, rates in Hz, latency in ms).

    ``stiffness_scale`` multiplies every stiffness term of the balloon (K_o scales by it, see
    :meth:`server.objects.balloon.BalloonParams.with_stiffness_scale`).

    Security (docs/security.md): ``token_file`` (lines ``TOKEN ROLE [NAME]``) or ``token`` (one
    token, role user) make every connection authenticate; a ``host`` that is not loopback
    requires one of them unless ``insecure``. ``tls_cert`` and ``tls_key`` (PEM files) serve
    https and wss. ``allow_origins`` are browser origins allowed besides the server's own.

    Agones (docs/deploy.md): with ``$AGONES_SDK_HTTP_PORT`` set the server reports to the SDK
    sidecar (:mod:`server.agones`) and asks to be shut down once it has been empty for
    ``agones_empty_shutdown_s`` [s] (None or 0: never).

    ``metrics_token_file`` holds the token a Prometheus scrape of ``/metrics`` must present
    (``Authorization: Bearer``); without it only a server on loopback serves ``/metrics``.

    Rooms (docs/usage.md): ``rooms`` maps a room name to its keys (``[rooms.NAME]`` of the
    configuration file: :data:`server.config.ROOM_OPTIONS`), ``room_templates`` a template's
    name to its keys and ``prefix`` (``[room_templates.NAME]``); ``max_users`` (None: 32) is
    each room's cap of users unless its keys set one; ``max_rooms`` caps the rooms,
    the default one included; an on-demand room empty for ``room_idle_s`` [s] is closed.
    ``token_secret_file`` holds the secret room tokens are signed with (``haptic token``).

    Drain (docs/deploy.md): on SIGTERM or Ctrl-C the server drains
    (:meth:`server.app.ServerApp.drain`) within ``drain_grace_s`` [s]; with ``snapshot_dir``
    each room's object state is saved there, and a room made again resumes it
    (:mod:`server.snapshots`).

    ``room_processes`` runs each room's simulation in a process of its own
    (:mod:`server.room_process`): a slow room's tick then delays no other room.

    ``gravity_m_s2`` (``--gravity``, ``object`` fem only): the FEM solid's rest state is the one
    it sags to under its own weight, g [m/s^2] along -z (0: none; docs/fem.md, "Gravity").

    ``tick_priority`` (``"realtime"`` or ``"off"``; :func:`default_tick_priority`): the thread
    that ticks the rooms (the server's event loop, and each room process's) asks for a real-time
    priority where the OS allows it (:mod:`server.priority`; docs/fem.md, "Under load").
    """

    host: str = "127.0.0.1"
    port: int = 8765
    mesh: str = "balloon"
    mesh_scale: float | None = None
    mesh_size: float | None = None
    mesh_max_edge: float | None = None
    subdivisions: int = 4
    sim_rate_hz: float = 20.0
    damping: float | None = None
    stiffness_scale: float = 1.0
    primitive: str = "plane"
    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    loss: float = 0.0
    seed: int = 0
    duration_s: float | None = None
    token_file: str | None = None
    token: str | None = None
    allow_origins: tuple[str, ...] = ()
    tls_cert: str | None = None
    tls_key: str | None = None
    insecure: bool = False
    material: str | None = None
    object: str = "balloon"
    volume_cache: str | None = None
    agones_empty_shutdown_s: float | None = EMPTY_SHUTDOWN_S
    metrics_token_file: str | None = None
    rooms: dict[str, dict[str, Any]] = field(default_factory=dict)
    room_templates: dict[str, dict[str, Any]] = field(default_factory=dict)
    max_rooms: int = MAX_ROOMS
    max_users: int | None = None
    room_idle_s: float = ROOM_IDLE_S
    token_secret_file: str | None = None
    snapshot_dir: str | None = None
    drain_grace_s: float = DRAIN_GRACE_S
    room_processes: bool = False
    mesh_repair: bool = False
    inclusions: tuple[str, ...] = ()
    inclusion_materials: tuple[str, ...] = ()
    gravity_m_s2: float = 0.0
    fem_volume_edge_pads: float | None = None
    tick_priority: str = field(default_factory=lambda: default_tick_priority())


def default_tick_priority() -> str:
    """``tick_priority``'s default: ``$HAPTIC_TICK_PRIORITY`` if set, else ``"realtime"``.

    The thread that ticks the rooms asks for SCHED_FIFO at a low priority, or a negative nice
    where refused (:class:`server.priority.TickPriority`); ``"off"`` keeps the ordinary policy.
    The variable turns it off where the command line cannot (e.g. a benchmark's server process).
    """
    return os.environ.get("HAPTIC_TICK_PRIORITY", "realtime")


#: ``[rooms.NAME]`` keys that name a :class:`ServerOptions` field differently.
_ROOM_KEY_FIELDS = {"sim_rate": "sim_rate_hz", "gravity": "gravity_m_s2"}
#: ``[rooms.NAME]`` keys that are the room's caps (:class:`server.admission.RoomLimits`).
_ROOM_LIMIT_KEYS = ("max_users", "max_viewers")


def room_options(opts: ServerOptions, keys: Mapping[str, object]) -> ServerOptions:
    """The options of one room: ``opts`` with the room's keys (``[rooms.NAME]``) on top.

    Raises
    ------
    ValueError
        A key that is not a room's (:data:`server.config.ROOM_OPTIONS`).
    """
    changes: dict[str, object] = {}
    for key, value in keys.items():
        if key in _ROOM_LIMIT_KEYS or key == "prefix":
            continue
        name = _ROOM_KEY_FIELDS.get(key, key)
        if name not in ServerOptions.__dataclass_fields__:
            raise ValueError(f"{key!r} is not a room's option")
        changes[name] = value
    return replace(opts, **changes)  # type: ignore[arg-type]


def room_caps(opts: ServerOptions, keys: Mapping[str, object]) -> dict[str, int]:
    """A room's caps (:class:`server.admission.RoomLimits` fields): its ``max_users`` and
    ``max_viewers`` keys, else the server's ``max_users`` (``--max-users``) when set.

    The users a server admits at most are then ``max_rooms * max_users`` when no room sets its
    own: the capacity of the Agones ``users`` counter (deploy/agones/fleet.yaml).
    """
    caps = {k: int(keys[k]) for k in _ROOM_LIMIT_KEYS if k in keys}  # type: ignore[call-overload]
    if opts.max_users is not None:
        caps.setdefault("max_users", int(opts.max_users))
    return caps


def build_secret(opts: ServerOptions) -> bytes | None:
    """The room-token secret of ``token_secret_file`` (None without one).

    Raises
    ------
    ValueError
        As :func:`server.security.load_secret`.
    """
    return load_secret(opts.token_secret_file) if opts.token_secret_file else None


def build_room(
    opts: ServerOptions,
    name: str,
    keys: Mapping[str, object],
    link: LinkConditions,
    auth: TokenTable | None,
    secret: bytes | None,
) -> Room:
    """The room ``name``: its object, rates and caps from ``opts`` with ``keys`` on top.

    Its tokens are the server's (``auth``) and, with a ``secret``, the room tokens for ``name``
    (:class:`server.security.RoomTokens`, checked against the wall clock).

    Raises
    ------
    ValueError
        As :func:`room_options`, :func:`build_rates`, :func:`build_world`.
    """
    ropts = room_options(opts, keys)
    rates = build_rates(ropts)
    world = build_world(ropts, rates)
    caps = room_caps(opts, keys)
    room_auth: TokenTable | None = auth
    if secret is not None:
        room_auth = RoomTokens(name, auth, secret, time.time)
    return Room(world, rates, link=link, limits=RoomLimits(**caps), auth=room_auth)


class RoomTemplates:
    """Makes rooms on demand from ``[room_templates]`` (:class:`server.app.RoomMaker`).

    A name is allowed when it starts with a template's ``prefix`` ('' or no prefix: any name);
    the template with the longest matching prefix builds it (:func:`build_room`).

    Parameters
    ----------
    opts : ServerOptions
        The server's options (a template's keys go on top of them).
    templates : mapping of str to mapping
        Template name -> its keys and optional ``prefix``.
    link, auth, secret
        As :func:`build_room`.
    """

    def __init__(
        self,
        opts: ServerOptions,
        templates: Mapping[str, Mapping[str, object]],
        link: LinkConditions,
        auth: TokenTable | None,
        secret: bytes | None,
    ) -> None:
        self.opts = opts
        self.templates = dict(templates)
        self.link = link
        self.auth = auth
        self.secret = secret

    def template(self, name: str) -> str | None:
        """The template that builds room ``name`` (None: no template allows it)."""
        if not valid_room_name(name):
            return None
        best: tuple[int, str] | None = None
        for tname, keys in self.templates.items():
            prefix = str(keys.get("prefix", ""))
            if name.startswith(prefix) and (best is None or len(prefix) > best[0]):
                best = (len(prefix), tname)
        return best[1] if best is not None else None

    def allows(self, name: str) -> bool:
        """Whether some template builds room ``name``."""
        return self.template(name) is not None

    def admits(self, name: str, token: str | None) -> bool:
        """Whether a client with ``token`` (None: none) may have room ``name`` made.

        With tokens (``--token-file``, ``--token``, ``--token-secret-file``): a room token for
        room ``name`` (:func:`server.security.check_room_token`, not expired) or a server-wide
        token, in either role; the same check the room's ``hello`` makes
        (:class:`server.security.RoomTokens`). Without tokens: any client.
        """
        if self.auth is None and self.secret is None:
            return True
        return RoomTokens(name, self.auth, self.secret, time.time).check(token) is not None

    def build(self, name: str) -> Room:
        """Room ``name`` from its template. Raises ValueError (no template, bad keys)."""
        tname = self.template(name)
        if tname is None:
            raise ValueError(f"no room template allows the name {name!r}")
        log.info("building room %r from template %r", name, tname)
        return build_room(self.opts, name, self.templates[tname], self.link, self.auth, self.secret)


def room_spec(
    opts: ServerOptions,
    name: str,
    keys: Mapping[str, object],
    build: Callable[[], Room],
) -> RoomSpec:
    """How room ``name`` (``opts`` with ``keys`` on top) is built in a process of its own
    (``room_processes``); ``build`` builds it there (picklable).

    Raises
    ------
    ValueError
        As :func:`room_options` and :func:`build_rates` (checked here, before any process).
    """
    ropts = room_options(opts, keys)
    rates = build_rates(ropts)
    caps = room_caps(opts, keys)
    return RoomSpec(
        name=name,
        build=build,
        sim_rate_hz=rates.sim_rate_hz,
        max_users=RoomLimits(**caps).max_users,
        auth=opts.token_file is not None or opts.token is not None or bool(opts.token_secret_file),
        prefetch=_is_fem,
        log_level=logging.getLogger().getEffectiveLevel(),
        tick_priority=opts.tick_priority,
    )


def room_proxy(
    opts: ServerOptions,
    name: str,
    keys: Mapping[str, object],
    link: LinkConditions,
    auth: TokenTable | None,
    secret: bytes | None,
) -> RoomProxy:
    """Room ``name`` as :func:`build_room` builds it, in a process of its own.

    Raises
    ------
    ValueError
        As :func:`room_spec`.
    """
    build = functools.partial(build_room, opts, name, dict(keys), link, auth, secret)
    return RoomProxy(room_spec(opts, name, keys, build))


class ProcessRoomTemplates:
    """:class:`RoomTemplates` whose rooms each run in a process of their own."""

    def __init__(self, templates: RoomTemplates) -> None:
        self.templates = templates

    def allows(self, name: str) -> bool:
        """Whether some template builds room ``name``."""
        return self.templates.allows(name)

    def admits(self, name: str, token: str | None) -> bool:
        """As :meth:`RoomTemplates.admits`."""
        return self.templates.admits(name, token)

    def build(self, name: str) -> RoomProxy:
        """Room ``name``'s proxy (its process is started by the server). Raises ValueError."""
        tname = self.templates.template(name)
        if tname is None:
            raise ValueError(f"no room template allows the name {name!r}")
        keys = self.templates.templates[tname]
        build = functools.partial(self.templates.build, name)
        return RoomProxy(room_spec(self.templates.opts, name, keys, build))


def check_templates(opts: ServerOptions) -> None:
    """Build nothing, but check every template's keys once at the start (a bad template must
    fail the start, not the first join).

    Raises
    ------
    ValueError
        As :func:`room_options`, :func:`build_rates` and ``--gravity``'s check
        (:func:`build_world`) for a template's keys.
    """
    for tname, keys in opts.room_templates.items():
        try:
            build_rates(room_options(opts, keys))
            _check_gravity(room_options(opts, keys))
        except ValueError as exc:
            raise ValueError(f"[room_templates.{tname}]: {exc}") from None


def build_auth(opts: ServerOptions) -> TokenTable | None:
    """The tokens of these options, None when the server admits everyone.

    Raises
    ------
    ValueError
        Both or a malformed token source; a host off loopback without tokens nor ``insecure``.
    """
    if opts.token_file and opts.token:
        raise ValueError("give --token-file or --token, not both")
    auth: TokenTable | None = None
    if opts.token_file:
        auth = TokenTable.load(opts.token_file)
    elif opts.token:
        auth = TokenTable.single(opts.token)
    if (
        auth is None
        and not opts.token_secret_file
        and not is_loopback(opts.host)
        and not opts.insecure
    ):
        raise ValueError(
            f"refusing to listen on {opts.host} without tokens: anyone who can reach it could "
            "push every user's hand. Give --token-file FILE, --token TOKEN or "
            "--token-secret-file FILE (and --tls-cert/--tls-key), or --insecure to accept that "
            "risk (docs/security.md)"
        )
    return auth


def build_metrics_token(opts: ServerOptions) -> TokenTable | None:
    """The token of ``metrics_token_file`` (its one line, whitespace stripped); None without.

    Raises
    ------
    ValueError
        A file that cannot be read, or whose content is not one token (16-256 printable
        characters without spaces or ``#``); the message never shows the file's content.
    """
    if not opts.metrics_token_file:
        return None
    try:
        text = Path(opts.metrics_token_file).read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read the metrics token file: {exc}") from None
    try:
        return TokenTable.single(text)
    except ValueError:
        raise ValueError(
            f"{opts.metrics_token_file}: the metrics token file must hold one token of 16-256 "
            "printable characters without spaces or #"
        ) from None


def build_ssl(opts: ServerOptions) -> ssl.SSLContext | None:
    """The TLS context of ``tls_cert``/``tls_key``, None without them.

    Raises
    ------
    ValueError
        Only one of the two given, or files that do not hold a matching certificate and key.
    """
    if not opts.tls_cert and not opts.tls_key:
        return None
    if not (opts.tls_cert and opts.tls_key):
        raise ValueError("--tls-cert and --tls-key go together")
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(opts.tls_cert, opts.tls_key)
    except (OSError, ssl.SSLError) as exc:
        raise ValueError(f"cannot load the TLS certificate or key: {exc}") from None
    return ctx


def build_link(opts: ServerOptions) -> LinkConditions:
    """The injected link conditions of ``--latency-ms``, ``--jitter-ms`` and ``--loss``.

    Built once per server (:func:`run_server`): the connections are shaped by them and the room
    announces them to clients.

    Raises
    ------
    ValueError
        Latency or jitter outside [0, 60000] ms, loss outside [0, 1), or a non-finite value; the
        message names the setting (:meth:`shared.protocol.LinkConditions.checked`).
    """
    return LinkConditions.checked(opts.latency_ms, opts.jitter_ms, opts.loss)


def build_agones(opts: ServerOptions) -> AgonesOptions:
    """The Agones agent's options (used only under Agones: ``$AGONES_SDK_HTTP_PORT`` set).

    Labels the GameServer with the object model (``agones.dev/sdk-object``: balloon or fem) and
    the protocol version (``agones.dev/sdk-protocol``), so that an allocation can select on them.

    Raises
    ------
    ValueError
        ``agones_empty_shutdown_s`` negative or not finite, or ``$AGONES_SDK_HTTP_PORT`` set to
        something that is not a port (:meth:`server.agones.AgonesSDK.from_environ`).
    """
    empty = opts.agones_empty_shutdown_s
    if empty is not None and not (math.isfinite(empty) and empty >= 0.0):
        raise ValueError(f"--agones-empty-shutdown must be a number of seconds >= 0, got {empty}")
    AgonesSDK.from_environ()
    return AgonesOptions(
        empty_shutdown_s=empty or None,
        labels={"object": opts.object, "protocol": str(PROTOCOL_VERSION)},
        max_rooms=opts.max_rooms,
        max_users=users_admitted(opts),
    )


def users_admitted(opts: ServerOptions) -> int:
    """The users a server of these options admits at most [users]: the default room's cap, each
    configured room's, and the largest template's for every other slot of ``max_rooms``
    (:func:`room_caps`; 32 a room where nothing sets ``max_users``)."""

    def cap(keys: Mapping[str, object]) -> int:
        return int(room_caps(opts, keys).get("max_users", RoomLimits().max_users))

    total = cap({}) + sum(cap(keys) for keys in opts.rooms.values())
    free = max(0, opts.max_rooms - 1 - len(opts.rooms))
    if free and opts.room_templates:
        total += free * max(cap(keys) for keys in opts.room_templates.values())
    return total


def build_rates(opts: ServerOptions) -> Rates:
    """The server's rates: the clients' servo rate :data:`CLIENT_SERVO_RATE_HZ` and ``--sim-rate``.

    Built once per server (:func:`run_server`); the object, the world and the room all take their
    simulation period from it.

    Raises
    ------
    ValueError
        ``--sim-rate`` outside [1, 1000] Hz, or not dividing the servo rate (N = servo rate /
        simulation rate must be whole: the lifted loop, paper section 3); the message lists the
        rates that do.
    """
    if not (1.0 <= opts.sim_rate_hz <= 1000.0):
        raise ValueError(f"--sim-rate must be in [1, 1000] Hz, got {opts.sim_rate_hz:g}")
    try:
        return Rates(CLIENT_SERVO_RATE_HZ, opts.sim_rate_hz)
    except ValueError:
        ok = ", ".join(f"{r:g}" for r in dividing_rates(CLIENT_SERVO_RATE_HZ, 10.0, 250.0))
        raise ValueError(
            f"--sim-rate {opts.sim_rate_hz:g} Hz: a {CLIENT_SERVO_RATE_HZ:g} Hz servo loop is not "
            f"a whole multiple of it (N = {CLIENT_SERVO_RATE_HZ / opts.sim_rate_hz:.3g}), so "
            f"clients could not render its patches; use a rate that divides "
            f"{CLIENT_SERVO_RATE_HZ:g} Hz: {ok} Hz"
        ) from None


def build_world(opts: ServerOptions, rates: Rates | None = None):  # type: ignore[no-untyped-def]
    """The world for these options: the default balloon, a stress shape or a mesh file,
    factorized once.

    ``mesh``: ``balloon`` (icosphere of ``subdivisions``), a name of
    :data:`server.objects.shapes.STRESS_MESHES` (torus, box, plate, bowl, noisy-sphere,
    uneven) or a mesh file; ``mesh_scale``/``mesh_size`` apply to the last two,
    ``mesh_max_edge`` (refinement, :func:`server.objects.mesh.refine_mesh`) to all three.

    ``object``: ``balloon`` (the water balloon, :mod:`server.objects.balloon`) or ``fem`` (a
    tetrahedral elastic solid of that surface, :mod:`server.objects.fem`, whose ``material`` is
    a solid preset or file, :mod:`server.solid_materials`; its volume mesh is cached in
    ``volume_cache``).

    The object steps with ``rates.sim_period_s`` and the world keeps ``rates`` (default:
    :func:`build_rates` of ``opts``; given, its simulation rate must be ``opts.sim_rate_hz``).

    Raises
    ------
    ValueError
        A mesh that cannot be loaded, stays open, is not manifold or one body, is degenerate
        or of an absurd size (:class:`server.objects.mesh.MeshError`), or a ``mesh`` that is
        neither a known name nor an existing file; bad parameters; as
        :func:`build_rates`; ``rates`` that disagree with ``opts.sim_rate_hz``.
    """
    from haptic_collab.server.materials import load_material, material_to_params, top_side_stiffness
    from haptic_collab.server.objects.balloon import Balloon, BalloonParams
    from haptic_collab.server.objects.mesh import default_balloon, mesh_warnings, refine_mesh
    from haptic_collab.server.objects.shapes import load_object_mesh

    if rates is None:
        rates = build_rates(opts)
    elif not math.isclose(rates.sim_rate_hz, opts.sim_rate_hz, rel_tol=1e-9):
        raise ValueError(
            f"rates at {rates.sim_rate_hz:g} Hz disagree with --sim-rate {opts.sim_rate_hz:g} Hz"
        )
    element: Literal["auto", "p1", "anp", "p2"] = "auto"  # the FEM solid's (FemParams.element)
    if opts.mesh == "balloon":
        if not 0 <= opts.subdivisions <= 7:
            raise ValueError("--subdivisions must be in [0, 7]")
        shown = default_balloon(subdivisions=opts.subdivisions)
        mesh = shown
        if opts.object == "fem" and opts.mesh_max_edge is None:
            from haptic_collab.server.objects.fem import sphere_for_solid

            mesh, element = sphere_for_solid(opts.subdivisions)  # P2: shown split four ways
        if opts.mesh_max_edge is not None:
            mesh = refine_mesh(mesh, opts.mesh_max_edge, where="balloon")
    else:
        mesh = load_object_mesh(
            opts.mesh,
            scale=opts.mesh_scale,
            target_size_m=opts.mesh_size,
            max_edge_m=opts.mesh_max_edge,
            repair=opts.mesh_repair,
        )
    scale = float(opts.stiffness_scale)
    if not (math.isfinite(scale) and scale > 0.0):
        raise ValueError(f"--stiffness-scale must be a finite number > 0, got {scale:g}")
    base = BalloonParams(sim_period_s=rates.sim_period_s)
    if opts.material is not None and opts.object == "balloon":
        material = load_material(opts.material)
        base = material_to_params(material, base, volume_m3=float(mesh.volume))
        log.info("material %s", material.summary())
    if opts.object not in ("balloon", "fem"):
        raise ValueError(f"--object must be balloon or fem, got {opts.object!r}")
    if opts.inclusions and opts.object != "fem":
        raise ValueError("--inclusion needs --object fem (an inclusion is a region of the solid)")
    if opts.object == "fem" and opts.damping is not None:
        raise ValueError("--damping is the balloon's; a FEM solid's damping is its material's")
    _check_gravity(opts)
    params = base.with_stiffness_scale(scale)
    if opts.damping is not None:
        params = replace(params, damping=opts.damping)
    # the surface users touch: a P2 solid on the parent sphere shows the icosphere asked for
    touched = shown if opts.mesh == "balloon" and opts.mesh_max_edge is None else mesh
    for warning in mesh_warnings(touched, params.patch_radius_m, where=opts.mesh):
        log.warning("%s", warning)
    if opts.object == "fem":
        # with inclusions, P2 on the parent sphere unless their refinement makes it too large:
        # then linear tetrahedra (averaged nodal pressure) on the sphere shown (_build_fem)
        p1_mesh = shown if opts.mesh == "balloon" and mesh is not shown else None
        return world_around(
            _build_fem(opts, mesh, rates, scale, element, p1_mesh=p1_mesh), opts, rates
        )
    obj = Balloon(mesh, params)
    log.info("K_o %.0f N/m at the top, %.0f N/m at the side", *top_side_stiffness(obj))
    return world_around(obj, opts, rates)


def _volume_edge(pads: float | None, default: float | None) -> float | None:
    """``--fem-volume-edge``: ``default`` when not given, else a finite number > 0 of pad radii
    (0 is refused; a huge value is no limit in effect)."""
    if pads is None:
        return default
    v = float(pads)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"--fem-volume-edge must be a number of pad radii > 0, got {pads!r}")
    return v


def _check_gravity(opts: ServerOptions) -> None:
    """``--gravity``: a finite number in [0, GRAVITY_MAX_M_S2] m/s^2, and only for the FEM solid.

    Raises
    ------
    ValueError
        Out of range or not finite, or given (> 0) for the balloon, which has no weight model.
    """
    from haptic_collab.server.objects.fem import GRAVITY_MAX_M_S2

    g = float(opts.gravity_m_s2)
    if not (math.isfinite(g) and 0.0 <= g <= GRAVITY_MAX_M_S2):
        raise ValueError(
            f"--gravity must be in [0, {GRAVITY_MAX_M_S2:g}] m/s^2 (9.81 on Earth), got {g:g}"
        )
    if g > 0.0 and opts.object != "fem":
        raise ValueError("--gravity needs --object fem (the balloon has no weight model)")


def world_around(obj: Any, opts: ServerOptions, rates: Rates | None = None):  # type: ignore[no-untyped-def]
    """A new World around an object :func:`build_world` built for ``opts`` (its primitive and
    rates; ``rates`` default :func:`build_rates` of ``opts``). The object is used as it is: one
    reused for another World must be reset first (``obj.reset``).

    Raises
    ------
    ValueError
        As :func:`build_rates`, or an object stepping at another period than the rates'.
    """
    from haptic_collab.server.world import World

    return World(
        obj,
        primitive=opts.primitive,  # type: ignore[arg-type]
        rates=rates if rates is not None else build_rates(opts),
    )


def _build_fem(
    opts: ServerOptions,
    mesh: Any,
    rates: Rates,
    scale: float,
    element: Literal["auto", "p1", "anp", "p2"] = "auto",
    p1_mesh: Any = None,
) -> Any:
    """The FEM solid of ``--object fem`` (:func:`build_world`); E is multiplied by ``scale``;
    ``element`` is :attr:`server.objects.fem.FemParams.element`.

    With inclusions, ``mesh`` the parent sphere of a P2 solid and ``p1_mesh`` the sphere shown:
    the inclusions' surfaces refine the volume mesh around them, so where its P2 solid would
    have more than :data:`server.objects.fem.P2_MAX_NODES` nodes (the start-up took 61 s with
    two 162-vertex lumps, 23 s with 42-vertex ones; docs/palpation.md) the solid is linear, with
    averaged nodal pressure, on ``p1_mesh`` instead."""
    from haptic_collab.server.objects.fem import (
        P2_MAX_NODES,
        FemParams,
        FemSolid,
        p2_node_count,
        tet_edge_limit_m,
    )
    from haptic_collab.server.solid_materials import (
        SOLID_PRESETS,
        load_solid_material,
        solid_to_params,
    )

    material = load_solid_material(opts.material) if opts.material else SOLID_PRESETS["liver"]
    params = solid_to_params(material, FemParams(sim_period_s=rates.sim_period_s))
    params = replace(
        params,
        young_pa=params.young_pa * scale,
        gravity_m_s2=float(opts.gravity_m_s2),
        element=element,
        volume_edge_pads=_volume_edge(opts.fem_volume_edge_pads, params.volume_edge_pads),
    )
    log.info("FEM solid, material %s", material.summary())
    from haptic_collab.server.objects.inclusions import (
        element_materials,
        load_inclusions,
        volume_with_inclusions,
    )

    inclusions = load_inclusions(opts.inclusions, opts.inclusion_materials)
    if inclusions:
        edge = tet_edge_limit_m(params, float(mesh.volume))
        volume = volume_with_inclusions(
            mesh, inclusions, cache_dir=opts.volume_cache, max_edge_m=edge
        )
        p2_nodes = p2_node_count(volume[1]) if p1_mesh is not None else 0
        if p2_nodes > P2_MAX_NODES:
            log.info(
                "FEM solid: the inclusions refine the volume mesh to %d quadratic (P2) nodes, "
                "more than %d: linear tetrahedra with averaged nodal pressure on the %d-vertex "
                "sphere",
                p2_nodes,
                P2_MAX_NODES,
                len(p1_mesh.vertices),
            )
            mesh, params = p1_mesh, replace(params, element="anp")
            volume = volume_with_inclusions(
                mesh, inclusions, cache_dir=opts.volume_cache, max_edge_m=edge
            )
        materials = element_materials(*volume, material, inclusions, young_scale=scale)
        for inc in inclusions:
            log.info("inclusion %s: %s", inc.where, inc.material.summary())
        log.info("FEM solid: tetrahedra per material %s", materials.counts())
        obj = FemSolid(
            mesh, params, volume=volume, cache_dir=opts.volume_cache, materials=materials
        )
    else:
        obj = FemSolid(mesh, params, cache_dir=opts.volume_cache)
    log.info(
        "FEM solid: %d nodes, %d tetrahedra, %.3f kg; lowest modes %s Hz",
        len(obj.nodes),
        len(obj.tets),
        obj.mass_kg,
        ", ".join(f"{f:.1f}" for f in obj.natural_frequencies_hz[:3]),
    )
    if params.gravity_m_s2 > 0.0:
        log.info(
            "FEM solid: at rest sagged under its own weight (g %.4g m/s^2), %.1f mm at most",
            params.gravity_m_s2,
            1e3 * obj.sag_m,
        )
    from haptic_collab.server.materials import top_side_stiffness

    log.info("K_o %.0f N/m at the top, %.0f N/m at the side", *top_side_stiffness(obj))  # type: ignore[arg-type]
    return obj


async def _drain(
    app: ServerApp, grace_s: float, serving: asyncio.Future[None], again: asyncio.Event
) -> None:
    """Drain ``app`` after a signal (:meth:`server.app.ServerApp.drain`), for at most
    ``grace_s`` [s]; a second signal (``again`` set again) or the server's own end cuts it
    short. Never raises: the stop follows whatever happened."""
    again.clear()
    draining = asyncio.ensure_future(app.drain(grace_s))
    second = asyncio.ensure_future(again.wait())
    try:
        waits: set[asyncio.Future[Any]] = {draining, second, serving}
        await asyncio.wait(waits, timeout=grace_s, return_when=asyncio.FIRST_COMPLETED)
    finally:
        second.cancel()
        if not draining.done():
            draining.cancel()
            log.warning("the drain did not end within %g s: stopping now", grace_s)
        with contextlib.suppress(asyncio.CancelledError):
            try:
                await draining
            except Exception:  # noqa: BLE001 - the stop must follow
                log.exception("the drain failed")


def _is_fem(room: Room) -> bool:
    """Whether a room's object is a FEM solid (its patches are prefetched)."""
    from haptic_collab.server.objects.fem import FemSolid

    return isinstance(getattr(room.world, "obj", None), FemSolid)


def _room_gate(agent: AgonesAgent | None) -> Callable[[str], Awaitable[str | None]] | None:
    """The app's ``room_gate`` under Agones: :meth:`AgonesAgent.claim_room` in a thread."""
    if agent is None:
        return None
    claim = agent.claim_room
    return lambda name: asyncio.to_thread(claim, name)


async def run_server(opts: ServerOptions, on_ready: Callable[[int], None] | None = None) -> None:
    """Build everything, listen, and serve until cancelled or ``duration_s`` elapses."""
    link = build_link(opts)
    agones = build_agones(opts)
    auth = build_auth(opts)
    metrics_token = build_metrics_token(opts)
    ssl_context = build_ssl(opts)
    origins = tuple(normalize_origin(o) for o in opts.allow_origins)
    secret = build_secret(opts)
    if DEFAULT_ROOM in opts.rooms:
        raise ValueError(f"[rooms.{DEFAULT_ROOM}]: the default room is the top-level options'")
    if 1 + len(opts.rooms) > opts.max_rooms:
        raise ValueError(
            f"{1 + len(opts.rooms)} rooms (the default one and {len(opts.rooms)} [rooms]) but "
            f"max_rooms is {opts.max_rooms}"
        )
    check_templates(opts)
    grace = float(opts.drain_grace_s)
    if not (math.isfinite(grace) and grace > 0.0):
        raise ValueError(f"--drain-grace-s must be a number of seconds > 0, got {grace:g}")
    snapshot_dir = check_directory(opts.snapshot_dir) if opts.snapshot_dir else None
    # under Agones the agent starts now, before the rooms are built and the port listens (a FEM
    # solid takes seconds to build): it sends health pings from here on and calls Ready once
    # every room ticks (server/agones.py)
    apps: list[ServerApp] = []
    agents: list[AgonesAgent] = []
    agent = start_agones(lambda: apps[0].room_reports() if apps else [], agones)
    if agent is not None:
        agents.append(agent)
    try:
        make = room_proxy if opts.room_processes else build_room
        room = make(opts, DEFAULT_ROOM, {}, link, auth, secret)
        rooms = {}
        for name, keys in opts.rooms.items():
            try:
                rooms[name] = make(opts, name, keys, link, auth, secret)
            except ValueError as exc:
                raise ValueError(f"[rooms.{name}]: {exc}") from None
    except BaseException:
        for a in agents:
            await asyncio.to_thread(a.stop)
        raise
    rates = build_rates(opts)
    plain = (
        RoomTemplates(opts, opts.room_templates, link, auth, secret)
        if opts.room_templates
        else None
    )
    templates: RoomTemplates | ProcessRoomTemplates | None = plain
    if plain is not None and opts.room_processes:
        templates = ProcessRoomTemplates(plain)
    app = ServerApp(
        room,
        opts.host,
        opts.port,
        link=link,
        seed=opts.seed,
        ssl_context=ssl_context,
        allowed_origins=origins,
        # the FEM solid's patch solves (50 ms at 10k vertices) are its p99; the balloon's are
        # about 1 ms, and its demo stress set was not yet measured with a prefetching thread
        prefetch=_is_fem,
        metrics_token=metrics_token,
        rooms=rooms,
        room_maker=templates,
        max_rooms=opts.max_rooms,
        # with tokens, a room is made only for a client whose token names it (or a server-wide
        # token): a handshake alone costs no room
        room_admits=(
            templates.admits if templates and (auth is not None or secret is not None) else None
        ),
        # under Agones a room made on demand is put in the rooms list first; a full list
        # refuses it (the fleet sees this server as full, as it is)
        room_gate=_room_gate(agent),
        room_idle_s=opts.room_idle_s,
        snapshot_dir=snapshot_dir,
        tick_priority=opts.tick_priority,
    )
    scheme = "https" if ssl_context else "http"
    if auth is None and not is_loopback(opts.host):
        log.warning("--insecure: anyone who can reach %s may join and push", opts.host)
    elif ssl_context is None and not is_loopback(opts.host):
        log.warning("no TLS: tokens and forces cross the network in clear (give --tls-cert)")

    apps.append(app)

    def ready(port: int) -> None:
        info = room.object_info
        log.info(
            "serving %d-vertex object at %g Hz on %s://%s:%d/ (websocket /ws, %s)%s",
            info.n_vertices,
            rates.sim_rate_hz,
            scheme,
            opts.host,
            port,
            f"{len(auth)} tokens" if auth is not None else "no tokens",
            f"; injecting {opts.latency_ms:g} +- {opts.jitter_ms:g} ms, loss {opts.loss:g}"
            if link.active
            else "",
        )
        hint = "#token=YOUR_TOKEN" if auth is not None else ""
        missing = app.viewer_missing()
        if missing:
            log.warning(
                "the viewer is incomplete (%s missing under %s): the page will not load; "
                "in a source checkout run `make web-install` (npm ci in web/)",
                ", ".join(missing),
                app.web_dir,
            )
        for url in viewer_urls(opts.host, port, scheme):
            print(f"viewer: {url}{hint}", flush=True)
        for name in rooms:
            log.info("room %r: %s%s", name, room_page_path(name), hint)
        if opts.room_processes:
            log.info("each room runs in a process of its own (--room-processes)")
        if templates is not None:
            log.info(
                "rooms on demand from templates %s (at most %d rooms)",
                ", ".join(f"{t!r}" for t in opts.room_templates),
                opts.max_rooms,
            )
        if on_ready:
            on_ready(port)

    # Ctrl-C and SIGTERM (`docker stop`, Kubernetes, a service manager) drain the server: no
    # new connection or room, every room's state saved (--snapshot-dir), every client told
    # server_draining and closed with code 1012, then the stop, all within --drain-grace-s; a
    # second signal stops at once. Installed here rather than left to asyncio.run's own SIGINT
    # handling, which is absent when the server inherits SIGINT as ignored (started in the
    # background by a non-interactive shell): Ctrl-C then did nothing.
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    signals: list[signal.Signals] = []

    def on_signal(sig: signal.Signals) -> None:
        signals.append(sig)
        if len(signals) == 1:
            log.info("%s: stopping (draining within %g s)", sig.name, grace)
        else:
            log.warning("%s again: stopping now", sig.name)
        stop.set()

    handled: list[signal.Signals] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, on_signal, sig)  # main thread only
            handled.append(sig)
    serving = asyncio.ensure_future(app.run(opts.duration_s, on_ready=ready))
    stopping = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait({serving, stopping}, return_when=asyncio.FIRST_COMPLETED)
        if not serving.done():  # a signal: drain, then app.run's own cleanup stops everything
            await _drain(app, grace, serving, stop)
            serving.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await serving
        else:
            serving.result()  # re-raise a failure to start (a bad port, a bad certificate)
    finally:
        for agent in agents:
            await asyncio.to_thread(agent.stop)
        stopping.cancel()
        if not serving.done():  # run_server itself was cancelled
            serving.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await serving
        for sig in handled:
            loop.remove_signal_handler(sig)
