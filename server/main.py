"""``haptic server``: build the object and the room, serve them over websockets."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from server.app import ServerApp
from server.latency import LinkConfig
from server.room import Room
from shared.protocol import LinkConditions

log = logging.getLogger("haptic.server")


@dataclass
class ServerOptions:
    """Options of ``haptic server`` (SI units, rates in Hz, latency in ms).

    ``stiffness_scale`` multiplies every stiffness term of the balloon (K_o scales by it, see
    :meth:`server.objects.balloon.BalloonParams.with_stiffness_scale`).
    """

    host: str = "127.0.0.1"
    port: int = 8765
    mesh: str = "balloon"
    mesh_scale: float | None = None
    mesh_size: float | None = None
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


def build_world(opts: ServerOptions):  # type: ignore[no-untyped-def]
    """The world for these options: the default balloon or a mesh file, factorized once.

    Raises
    ------
    ValueError
        A mesh that cannot be loaded, stays open or is degenerate; bad parameters.
    """
    from server.objects.balloon import Balloon, BalloonParams
    from server.objects.mesh import default_balloon, load_mesh
    from server.world import World

    if not (1.0 <= opts.sim_rate_hz <= 1000.0):
        raise ValueError(f"--sim-rate must be in [1, 1000] Hz, got {opts.sim_rate_hz:g}")
    if opts.mesh == "balloon":
        if not 0 <= opts.subdivisions <= 7:
            raise ValueError("--subdivisions must be in [0, 7]")
        mesh = default_balloon(subdivisions=opts.subdivisions)
    else:
        mesh = load_mesh(Path(opts.mesh), scale=opts.mesh_scale, target_size_m=opts.mesh_size)
    scale = float(opts.stiffness_scale)
    if not (math.isfinite(scale) and scale > 0.0):
        raise ValueError(f"--stiffness-scale must be a finite number > 0, got {scale:g}")
    params = BalloonParams(sim_period_s=1.0 / opts.sim_rate_hz).with_stiffness_scale(scale)
    if opts.damping is not None:
        params = replace(params, damping=opts.damping)
    obj = Balloon(mesh, params)
    return World(obj, primitive=opts.primitive)  # type: ignore[arg-type]


async def run_server(opts: ServerOptions, on_ready: Callable[[int], None] | None = None) -> None:
    """Build everything, listen, and serve until cancelled or ``duration_s`` elapses."""
    link = LinkConfig(latency_ms=opts.latency_ms, jitter_ms=opts.jitter_ms, loss=opts.loss)
    world = build_world(opts)
    room = Room(
        world,
        opts.sim_rate_hz,
        link=LinkConditions(latency_ms=opts.latency_ms, jitter_ms=opts.jitter_ms, loss=opts.loss),
    )
    app = ServerApp(room, opts.host, opts.port, link=link, seed=opts.seed)

    def ready(port: int) -> None:
        info = room.object_info
        log.info(
            "serving %d-vertex object at %g Hz on http://%s:%d/ (websocket /ws)%s",
            info.n_vertices,
            opts.sim_rate_hz,
            opts.host,
            port,
            f"; injecting {opts.latency_ms:g} +- {opts.jitter_ms:g} ms, loss {opts.loss:g}"
            if link.active
            else "",
        )
        print(f"viewer: http://{opts.host}:{port}/", flush=True)
        if on_ready:
            on_ready(port)

    await app.run(opts.duration_s, on_ready=ready)
