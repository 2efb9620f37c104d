"""Benchmark of the simulation core: per-tick cost of :meth:`server.world.World.tick`.

For each mesh size the default balloon is built (operators, ordering, one factorization: timed as
``build_s``), then for each number of users a fresh run of ticks is timed. Users are spread over
the balloon (not on the fixed base), press 2-5 mm in with a proportional local model
``f = K_h * e`` (``K_h = 0.5 K_o_eff`` from the last output, section 6 Step 2), and their probes
drift about 0.3 mm per tick along the surface with 0.1 mm jitter, so that the patch cache sees
the misses a slowly moving hand causes. The first ``warmup`` ticks (every patch solved for the
first time) are reported apart as ``first_tick_ms``. Each run is timed twice, side by side on
the same object and the same motion: with the proxy following the surface (the product,
``median_ms``) and with the closest point of the surface every tick (the paper's Step 1 read
literally, ``closest_median_ms``); ``proxy_cost_ratio`` is the first over the second.

:func:`bench_room` times the server's whole simulation tick (:meth:`server.room.Room.tick`:
forces bounded, the world, gain advice, patches and viewer frames encoded) with ``haptic bench
load``'s scripted users and viewers but no sockets, in CPU time as well as wall time, so that a
slower room can be told from a busier machine.

:func:`bench_viewer_stream` measures what one viewer receives per second while a user presses a
10k-vertex balloon: the float32 positions sent every tick before (``VTX1``) against the
displacement stream (:mod:`server.viewer_stream`), as payload and as wire bytes (payload plus
websocket frame header: the server negotiates no compression).

This is the only server module allowed to read a clock (``time.perf_counter``).
"""

from __future__ import annotations

import ctypes
import json
import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from haptic_collab.server.objects.balloon import Balloon, BalloonParams
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.viewer_decoder import ViewerStreamDecoder
from haptic_collab.server.viewer_stream import (
    DEFAULT_BYTES_PER_S,
    ViewerStream,
)
from haptic_collab.server.world import ContactInput, World
from haptic_collab.shared.protocol import encode_faces, encode_vertices

#: (setter, getter) symbol pairs of the OpenBLAS builds numpy and scipy ship
_BLAS_THREAD_SYMBOLS = (
    ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
    ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
    ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
    ("openblas_set_num_threads", "openblas_get_num_threads"),
)


@contextmanager
def single_thread_blas() -> Iterator[int]:
    """Run the enclosed code with every loaded OpenBLAS limited to one thread (best effort).

    The benchmark measures one core: a multi-threaded BLAS inside the sparse solves only adds
    spin-waiting on a busy machine. Finds the loaded OpenBLAS libraries (Linux
    ``/proc/self/maps``) and calls their ``set_num_threads``, restoring the old counts after.
    Yields the number of libraries limited (0 where this is not possible).
    """
    restore: list[tuple[Any, int]] = []
    try:
        with open("/proc/self/maps", encoding="utf-8") as maps:
            paths = sorted({line.split()[-1] for line in maps if "openblas" in line.lower()})
    except OSError:
        paths = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for setter, getter in _BLAS_THREAD_SYMBOLS:
            if hasattr(lib, setter) and hasattr(lib, getter):
                get, put = getattr(lib, getter), getattr(lib, setter)
                get.restype = ctypes.c_int
                restore.append((put, int(get())))
                put(ctypes.c_int(1))
                break
    try:
        yield len(restore)
    finally:
        for put, count in restore:
            put(ctypes.c_int(count))


#: icosphere subdivision level for each supported vertex count
_SUBDIVISIONS = {10 * 4**s + 2: s for s in range(8)}


def _ticks_for(n_vertices: int, ticks: int | None) -> int:
    if ticks is not None:
        return ticks
    return 300 if n_vertices <= 12000 else 100


def _directions(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` unit vectors spread over the sphere above z = -0.6 (Fibonacci lattice)."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    k = np.arange(count) + 0.5
    z = 1.0 - 1.6 * k / count
    r = np.sqrt(1.0 - z * z)
    phi = golden * np.arange(count) + rng.uniform(0, 2 * math.pi)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _run_users(
    world: World,
    users: int,
    ticks: int,
    warmup: int,
    seed: int,
    prefetch: bool = False,
    stand_in: bool = True,
) -> dict[str, Any]:
    """Tick ``world`` with ``users`` pressing and drifting; with ``prefetch``, as the server
    runs it: a :class:`server.prefetch.PatchPrefetcher` (``stand_in`` passed on) after each tick
    and the rest of the simulation period idle (so the run takes ``ticks`` periods of
    wall-clock time)."""
    from haptic_collab.server.prefetch import PatchPrefetcher

    prefetcher = PatchPrefetcher(world, stand_in=stand_in) if prefetch else None
    period = float(world.sim_period_s)
    rng = np.random.default_rng(seed)
    centre, radius = world.rest_center, world.rest_radius_m
    dirs = _directions(users, rng)
    # a tangent drift direction per user
    helper = np.where(np.abs(dirs[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    drift = np.cross(dirs, helper)
    drift /= np.linalg.norm(drift, axis=1, keepdims=True)
    depth = rng.uniform(0.002, 0.005, users)
    forces = np.zeros((users, 3))
    gains = np.zeros(users)
    names = [f"user{i}" for i in range(users)]
    times_ms: list[float] = []
    cpu_ms: list[float] = []
    for _ in range(warmup + ticks):
        dirs = dirs + (3e-4 / radius) * drift + rng.normal(0.0, 1e-4 / radius, dirs.shape)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        dirs[:, 2] = np.maximum(dirs[:, 2], -0.6)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        probes = centre + dirs * (radius - depth[:, None])
        inputs = {n: ContactInput(probe=probes[i], force=forces[i]) for i, n in enumerate(names)}
        start, start_cpu = time.perf_counter(), time.thread_time()
        out = world.tick(inputs)
        cpu_ms.append((time.thread_time() - start_cpu) * 1e3)
        times_ms.append((time.perf_counter() - start) * 1e3)
        if prefetcher is not None:
            prefetcher.after_tick()
            time.sleep(max(0.0, start + period - time.perf_counter()))
        for i, n in enumerate(names):
            o = out[n]
            if gains[i] == 0.0:
                gains[i] = 0.5 * o.k_o_eff
            forces[i] = gains[i] * max(o.penetration_m, 0.0) * np.asarray(o.normal)
    if prefetcher is not None:
        prefetcher.close()
    steady = np.asarray(times_ms[warmup:])
    return {
        "users": users,
        "prefetch": prefetch,
        "ticks": ticks,
        "median_ms": float(np.median(steady)),
        "p99_ms": float(np.percentile(steady, 99)),
        "max_ms": float(np.max(steady)),
        "first_tick_ms": float(times_ms[0]),
        # the thread's CPU time: what a tick costs, less the time it waited for a core on a
        # busy machine (prefetch solves in another thread are not counted)
        "cpu_median_ms": float(np.median(cpu_ms[warmup:])),
    }


def bench_world(
    n_vertices_list: Sequence[int] = (2562, 10242, 40962),
    users_list: Sequence[int] = (1, 2, 8, 32),
    ticks: int | None = None,
    seed: int = 0,
    warmup: int = 3,
    params: BalloonParams | None = None,
) -> dict[str, Any]:
    """Time :meth:`World.tick` for each mesh size and number of users.

    Parameters
    ----------
    n_vertices_list : sequence of int
        Icosphere vertex counts (10 * 4**s + 2: 642, 2562, 10242, 40962, ...).
    users_list : sequence of int
        Numbers of simultaneous users.
    ticks : int, optional
        Timed ticks per run; default 300 up to 12k vertices, 100 above.
    seed : int
        Seed of the users' placement and motion.
    warmup : int
        Untimed-in-the-median first ticks of each run.
    params : BalloonParams, optional
        Balloon parameters (default :class:`BalloonParams`).

    Returns
    -------
    dict
        JSON-able: ``{"meshes": [{"n_vertices", "build_s", "runs": [{"users", "ticks",
        "median_ms", "p99_ms", "max_ms", "first_tick_ms", "cpu_median_ms", "solves_per_tick",
        "closest_median_ms", "closest_cpu_median_ms", "closest_p99_ms", "proxy_cost_ratio"}]}],
        ...}``. ``*_ms`` are wall-clock times [ms]; ``cpu_median_ms`` is the median of the
        ticking thread's CPU time (``time.thread_time``), which a busy machine inflates far less.

    Raises
    ------
    ValueError
        A vertex count that is not an icosphere size, or a non-positive user count.
    """
    p = params if params is not None else BalloonParams()
    for n in n_vertices_list:
        if n not in _SUBDIVISIONS:
            raise ValueError(f"{n} is not an icosphere vertex count (10 * 4**s + 2)")
    if any(u <= 0 for u in users_list):
        raise ValueError(f"user counts must be > 0, got {list(users_list)}")
    with single_thread_blas() as limited:
        meshes = [_bench_mesh(n, users_list, ticks, seed, warmup, p) for n in n_vertices_list]
    return {
        "benchmark": "world_tick",
        "blas_libraries_single_threaded": limited,
        "sim_period_s": p.sim_period_s,
        "patch_radius_m": p.patch_radius_m,
        "damping": p.damping,
        "meshes": meshes,
    }


def _bench_mesh(
    n: int, users_list: Sequence[int], ticks: int | None, seed: int, warmup: int, p: BalloonParams
) -> dict[str, Any]:
    """Build the ``n``-vertex balloon once (timed) and time a run per number of users."""
    mesh = default_balloon(0.1, _SUBDIVISIONS[n])
    start = time.perf_counter()
    obj = Balloon(mesh, p)
    build_s = time.perf_counter() - start
    runs = []
    for users in users_list:
        obj.reset(clear_cache=True)
        closest = _run_users(World(obj, proxy="closest"), users, _ticks_for(n, ticks), warmup, seed)
        obj.reset(clear_cache=True)
        world = World(obj)
        solves_before = obj.solve_count
        result = _run_users(world, users, _ticks_for(n, ticks), warmup, seed)
        result["solves_per_tick"] = (obj.solve_count - solves_before) / (warmup + result["ticks"])
        result["closest_median_ms"] = closest["median_ms"]
        result["closest_cpu_median_ms"] = closest["cpu_median_ms"]
        result["closest_p99_ms"] = closest["p99_ms"]
        result["proxy_cost_ratio"] = result["median_ms"] / max(closest["median_ms"], 1e-9)
        runs.append(result)
    return {"n_vertices": n, "build_s": build_s, "runs": runs}


def bench_fem(
    n_vertices_list: Sequence[int] = (642, 2562, 10242),
    users: int = 8,
    ticks: int = 100,
    seed: int = 0,
    warmup: int = 3,
    element: str = "auto",
) -> dict[str, Any]:
    """Start-up and tick cost of the FEM solid (``--object fem``, liver) on icospheres.

    ``element`` is :attr:`server.objects.fem.FemParams.element`: "auto" builds the solid as the
    server does (:func:`server.objects.fem.sphere_for_solid`: P2 on the parent icosphere up to
    2562 shown vertices); "p1" linear tetrahedra on the icosphere of ``n`` vertices itself.

    For each surface size: the volume mesh (TetGen in its own process, not cached), the
    assembly, the one sparse factorisation (geometric nested dissection, SuperLU without
    pivoting) and the modes [s]; then :meth:`World.tick` with ``users`` users pressing and
    drifting, as :func:`bench_world` [ms].

    Returns
    -------
    dict
        JSON-able: ``{"benchmark": "fem", "meshes": [{"n_vertices", "nodes", "tetrahedra",
        "dofs", "volume_mesh_s", "assembly_s", "factor_s", "modes_s", "factor_nnz",
        "users", "median_ms", "p99_ms", "max_ms", ...}]}``.
    """
    import tempfile

    from haptic_collab.server.objects.fem import FemParams, FemSolid, sphere_for_solid

    meshes = []
    with single_thread_blas() as limited, tempfile.TemporaryDirectory() as cache:
        for n in n_vertices_list:
            if n not in _SUBDIVISIONS:
                raise ValueError(f"{n} is not an icosphere vertex count (10 * 4**s + 2)")
            sub = _SUBDIVISIONS[n]
            surface, chosen = sphere_for_solid(sub)
            if element == "p1":
                surface, chosen = default_balloon(0.1, sub), "p1"
            obj = FemSolid(surface, FemParams(element=chosen), cache_dir=cache)
            row: dict[str, Any] = {
                "n_vertices": n,
                "element": obj.element,
                "nodes": len(obj.nodes),
                "tetrahedra": len(obj.tets),
                "factor_nnz": int(obj.factor_nnz),
                **obj.timings,
            }
            solves = obj.solve_count
            row.update(_run_users(World(obj), users, ticks, warmup, seed))
            row["patch_solves_on_tick"] = obj.solve_count - solves
            # as the server runs it: the patches ahead solved between ticks (server.prefetch),
            # without and with stand-in centres for a contact whose own is not solved yet
            for name, stand_in in (("prefetch", False), ("stand_in", True)):
                obj.reset(clear_cache=True)
                solves, ahead, stood = obj.solve_count, obj.prefetch_count, obj.stand_ins
                fetched = _run_users(
                    World(obj), users, ticks, warmup, seed, prefetch=True, stand_in=stand_in
                )
                row[name] = {
                    "median_ms": fetched["median_ms"],
                    "p99_ms": fetched["p99_ms"],
                    "max_ms": fetched["max_ms"],
                    "patch_solves_on_tick": obj.solve_count - solves,
                    "patches_prefetched": obj.prefetch_count - ahead,
                    "stand_ins": obj.stand_ins - stood,
                }
            meshes.append(row)
    return {"benchmark": "fem", "blas_libraries_single_threaded": limited, "meshes": meshes}


#: Phases of the press :func:`bench_viewer_stream` streams: (name, seconds).
PRESS_PHASES = (("rest", 1.0), ("press", 1.5), ("hold", 3.0), ("release", 1.0), ("after", 2.0))


class _WireBytes:
    """Bytes one websocket message takes on the wire from the server to a browser: the payload
    plus the 2-10 byte frame header (server frames are unmasked; the server negotiates no
    permessage-deflate: compression cost a fifth of its time under load, docs/bench-load.md)."""

    def __call__(self, payload: bytes) -> int:
        n = len(payload)
        return n + (2 if n < 126 else 4 if n < 65536 else 10)


def bench_viewer_stream(
    n_vertices: int = 10242,
    dent_m: float = 0.010,
    tremor_m: float = 5e-5,
    bytes_per_s: float | None = DEFAULT_BYTES_PER_S,
    seed: int = 0,
    params: BalloonParams | None = None,
) -> dict[str, Any]:
    """Bytes per second one viewer receives while a user presses the top of the balloon.

    The user holds its probe 2 mm into the top and its force follows :data:`PRESS_PHASES`: none
    (rest), a linear ramp over 1.5 s to ``F = K_o * dent_m`` (press), held with a hand tremor of
    ``K_o * tremor_m`` N standard deviation per tick (hold), a ramp back to none (release), none
    (after). Every tick the viewer gets the float32 frame of before (``VTX1``, n x 12 bytes) and,
    for comparison, the stream's frame (reported sent at once: an ideal link), which the
    reference decoder applies.

    Parameters
    ----------
    n_vertices : int
        Icosphere vertex count (10 * 4**s + 2).
    dent_m : float
        Static depth of the dent at the top under the full force [m].
    tremor_m : float
        Standard deviation of the hand tremor, as surface displacement at the top [m].
    bytes_per_s : float or None
        The stream's budget per viewer [bytes/s] (None: unlimited).
    seed : int
        Seed of the tremor.
    params : BalloonParams, optional
        Balloon parameters (default :class:`BalloonParams`, 20 Hz).

    Returns
    -------
    dict
        JSON-able: ``n_vertices``, ``sim_rate_hz``, ``frame_budget_bytes``, ``press_force_n``,
        ``dent_m`` (deepest displacement reached), ``join_bytes``, ``phases`` ({name: {
        ``seconds``, ``float32_bytes_per_s``, ``float32_wire_bytes_per_s``,
        ``stream_bytes_per_s``, ``stream_wire_bytes_per_s``, ``max_error_m`` (largest
        difference of the decoded surface from the server's), ``partial_frames``}}), ``press``
        (the same rates over press, hold and release together), ``peak_stream_bytes_per_s``
        (over any 1 s window).

    Raises
    ------
    ValueError
        A vertex count that is not an icosphere size.
    """
    if n_vertices not in _SUBDIVISIONS:
        raise ValueError(f"{n_vertices} is not an icosphere vertex count (10 * 4**s + 2)")
    p = params if params is not None else BalloonParams()
    rate = 1.0 / p.sim_period_s
    world = World(Balloon(default_balloon(0.1, _SUBDIVISIONS[n_vertices]), p))
    obj = world.obj
    rest = np.asarray(obj.rest_vertices)
    top = rest[int(np.argmax(rest[:, 2]))]
    probe = top - np.array([0.0, 0.0, 0.002])
    k_o = world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})["u"].k_o
    force_n = k_o * dent_m
    stream = ViewerStream.of_world(world, rate, bytes_per_s)
    decoder = ViewerStreamDecoder()
    join = [encode_faces(world.faces), *stream.join("v", 0, world.vertices)]
    for data in join[1:]:
        decoder.feed(data)
    rng = np.random.default_rng(seed)
    old_wire, new_wire = _WireBytes(), _WireBytes()
    rows: list[tuple[str, int, int, int, int, float, bool]] = []
    tick = 0
    deepest = 0.0
    for name, seconds in PRESS_PHASES:
        ticks = round(seconds * rate)
        for i in range(ticks):
            ramp = (i + 1) / ticks
            f = {"rest": 0.0, "press": ramp, "hold": 1.0, "release": 1.0 - ramp, "after": 0.0}
            push = f[name] * force_n
            if name == "hold":
                push += k_o * tremor_m * float(rng.normal())
            tick += 1
            world.tick({"u": ContactInput(probe=probe, force=np.array([0.0, 0.0, push]))})
            old = encode_vertices(tick, world.vertices)
            frame = stream.frames(tick, world.vertices, ["v"])["v"]
            frame.sent()
            decoder.feed(frame.data)
            err = float(np.max(np.linalg.norm(decoder.vertices - world.vertices, axis=1)))
            deepest = min(deepest, float(np.min(stream.displacement(world.vertices))))
            rows.append(
                (name, len(old), old_wire(old), len(frame.data), new_wire(frame.data), err,
                 frame.partial)
            )  # fmt: skip

    def rates(selected: list[tuple[str, int, int, int, int, float, bool]]) -> dict[str, Any]:
        k = max(len(selected), 1)
        return {
            "seconds": len(selected) / rate,
            "float32_bytes_per_s": sum(r[1] for r in selected) * rate / k,
            "float32_wire_bytes_per_s": sum(r[2] for r in selected) * rate / k,
            "stream_bytes_per_s": sum(r[3] for r in selected) * rate / k,
            "stream_wire_bytes_per_s": sum(r[4] for r in selected) * rate / k,
            "max_error_m": max((r[5] for r in selected), default=0.0),
            "partial_frames": sum(r[6] for r in selected),
        }

    window = max(1, round(rate))
    sizes = np.array([r[3] for r in rows], dtype=float)
    peak = np.convolve(sizes, np.ones(window), "valid").max() if len(sizes) >= window else 0.0
    return {
        "benchmark": "viewer_stream",
        "n_vertices": n_vertices,
        "sim_rate_hz": rate,
        "frame_budget_bytes": stream.frame_budget_bytes,
        "press_force_n": force_n,
        "dent_m": -deepest,
        "tremor_m": tremor_m,
        "join_bytes": sum(len(f) for f in join),
        "phases": {n: rates([r for r in rows if r[0] == n]) for n, _ in PRESS_PHASES},
        "press": rates([r for r in rows if r[0] in ("press", "hold", "release")]),
        "peak_stream_bytes_per_s": float(peak),
    }


def bench_gain_advice(users: int = 8, lookups: int = 20_000) -> dict[str, Any]:
    """Cost [us] the recommended gains add to a simulation tick, per user (:mod:`server.gains`).

    One design is made first (outside the timing, as the worker would); then ``lookups`` calls of
    :meth:`server.gains.GainAdvisor.recommend` for ``users`` users on the designed cell (the
    steady case) and as many on cells still missing (a miss queues a job, costs a lookup).
    """
    from haptic_collab.server.gains import GainAdvisor, run_job
    from haptic_collab.shared.protocol import DeviceInfo, Hello

    adv = GainAdvisor(20.0)
    dev = DeviceInfo(max_stiffness_n_per_m=1000.0, max_damping_n_s_per_m=10.0)
    hellos = [Hello(protocol=1, role="user", name=f"u{i}", device=dev) for i in range(users)]
    adv.recommend("u0", hellos[0], k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0)
    t0 = time.perf_counter()
    for job in adv.take_jobs():
        adv.store(job, run_job(job, adv.table.grid_ratio, adv.table.hand_box))
    design_s = time.perf_counter() - t0

    def timed(k_o: float) -> list[float]:
        out = []
        for i in range(lookups):
            name = f"u{i % users}"
            t = time.perf_counter()
            adv.recommend(name, hellos[i % users], k_o_eff=k_o, k_o_stiff=k_o, b_o=0.0)
            out.append((time.perf_counter() - t) * 1e6)
        return out

    hit = timed(300.0)
    miss = timed(3000.0)
    return {
        "benchmark": "gain_advice",
        "users": users,
        "design_s": design_s,
        "hit_us_p50": float(np.percentile(hit, 50)),
        "hit_us_p99": float(np.percentile(hit, 99)),
        "miss_us_p50": float(np.percentile(miss, 50)),
        "miss_us_p99": float(np.percentile(miss, 99)),
        "per_tick_us_p50_at_users": float(np.percentile(hit, 50)) * users,
    }


def bench_room(
    users: int = 32,
    viewers: int = 8,
    subdivisions: int = 4,
    ticks: int = 200,
    warmup: int = 30,
    sim_rate_hz: float = 20.0,
) -> dict[str, Any]:
    """Cost [ms] of :meth:`server.room.Room.tick` with ``haptic bench load``'s users and viewers,
    without sockets: the whole simulation tick of ``haptic server`` (forces bounded, the world
    ticked, gains recommended, patches, viewer frames and the room summary encoded) on one core.

    The room is built as ``haptic server`` builds it (:func:`server.main.build_world`); the users
    are :mod:`haptic_collab.bench.load_clients`' scripted users (resting 2 mm in at the top and
    side points, half of them pressing 3 mm more at 0.25 Hz, ``K_h = 0.5 K_o_eff``), each sending
    two ``state`` frames per tick with a 1 ms round trip; the viewers take every frame. The gain
    designs the ticks ask for are made during the warm-up (as the server's worker makes them), so
    the timed ticks find them. Wall time (``time.perf_counter``) and the thread's CPU time
    (``time.thread_time``: what the tick costs on a busy machine, less the time it waited for a
    core) are both reported, and the CPU time of the world's tick and of the gain advice apart.

    Parameters
    ----------
    users, viewers : int
        Scripted users (at most 32: the load bench's placements) and viewers.
    subdivisions : int
        Icosphere subdivisions of the default balloon (4: 2562 vertices).
    ticks, warmup : int
        Timed ticks, and ticks run before them.
    sim_rate_hz : float
        Simulation rate [Hz].

    Returns
    -------
    dict
        JSON-able: ``users``, ``viewers``, ``n_vertices``, ``ticks``; ``tick_ms_p50``,
        ``tick_ms_p99`` (wall), ``tick_cpu_ms_p50``, ``tick_cpu_ms_p99``, ``world_cpu_ms_p50``,
        ``gains_cpu_ms_p50`` [ms]; ``gain_hits``, ``gain_misses`` over the timed ticks.

    Raises
    ------
    ValueError
        More than 32 or fewer than 1 users, or a bad rate or mesh size (as ``haptic server``).
    """
    from haptic_collab.bench.load_clients import client_specs, user_hello, user_spot, user_state
    from haptic_collab.server.gains import run_job
    from haptic_collab.server.main import ServerOptions, build_rates, build_world
    from haptic_collab.server.room import Room

    if not 1 <= users <= 32:
        raise ValueError(f"users must be in [1, 32], got {users}")
    opts = ServerOptions(subdivisions=subdivisions, sim_rate_hz=sim_rate_hz)
    rates = build_rates(opts)
    room = Room(build_world(opts, rates), rates)
    period = 1.0 / room.sim_rate_hz
    obj = room.object_info.model_dump()
    specs = client_specs(users, viewers)
    spots = {}
    for i, spec in enumerate(specs):
        room.connect(spec.name, 0.0, address=f"127.0.0.{2 + i % 4}")
        if spec.role == "user":
            room.receive(spec.name, json.dumps(user_hello(spec)), 0.0)
            spots[spec.name] = user_spot(spec, obj)
        else:
            hello = {"type": "hello", "protocol": 1, "role": "viewer", "name": spec.name}
            room.receive(spec.name, json.dumps(hello), 0.0)
    user_specs = [s for s in specs if s.role == "user"]
    patches: dict[str, dict[str, Any] | None] = {s.name: None for s in user_specs}
    world, gains = room.world, room.gains
    cost = {"world": 0.0, "gains": 0.0}

    def timed(name: str, fn: Any) -> Any:
        def call(*args: Any, **kwargs: Any) -> Any:
            start = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                cost[name] += time.thread_time() - start

        return call

    world.tick = timed("world", world.tick)  # type: ignore[method-assign]
    gains.recommend = timed("gains", gains.recommend)  # type: ignore[method-assign]
    wall, cpu, world_ms, gains_ms = [], [], [], []
    seq = 0
    hits = misses = 0
    with single_thread_blas():
        room.start(0.0)
        for t in range(1, warmup + ticks + 1):
            seq += 1
            for half in (0.25, 0.75):  # two states per user per tick
                at = (t - 1 + half) * period
                for spec in user_specs:
                    state = user_state(
                        spec, spots[spec.name], at, patches[spec.name], seq, 1.0 + 0.1 * (seq % 7)
                    )
                    room.receive(spec.name, json.dumps(state), at)
                seq += 1
            if t == warmup + 1:
                hits, misses = gains.hits, gains.misses
            cost["world"] = cost["gains"] = 0.0
            start, start_cpu = time.perf_counter(), time.thread_time()
            out = room.tick(t, t * period)
            cpu.append((time.thread_time() - start_cpu) * 1e3)
            wall.append((time.perf_counter() - start) * 1e3)
            world_ms.append(cost["world"] * 1e3)
            gains_ms.append(cost["gains"] * 1e3)
            for o in out:
                if o.on_sent is not None:
                    o.on_sent()
                if o.stream == "patch" and isinstance(o.data, str):
                    patches[o.conn_id] = json.loads(o.data)
            if t <= warmup:  # the designs the server's worker would have made by now
                for job in gains.take_jobs():
                    gains.store(job, run_job(job, gains.table.grid_ratio, gains.table.hand_box))
    steady = slice(warmup, None)
    return {
        "benchmark": "room_tick",
        "users": users,
        "viewers": viewers,
        "n_vertices": int(world.n_vertices),
        "ticks": ticks,
        "tick_ms_p50": float(np.median(wall[steady])),
        "tick_ms_p99": float(np.percentile(wall[steady], 99)),
        "tick_cpu_ms_p50": float(np.median(cpu[steady])),
        "tick_cpu_ms_p99": float(np.percentile(cpu[steady], 99)),
        "world_cpu_ms_p50": float(np.median(world_ms[steady])),
        "gains_cpu_ms_p50": float(np.median(gains_ms[steady])),
        "gain_hits": gains.hits - hits,
        "gain_misses": gains.misses - misses,
    }


def measure() -> dict[str, Any]:
    """The default benchmark (about 1-2 minutes): world ticks, the viewer stream, gain advice.

    Returns
    -------
    dict
        The :func:`bench_world` result with ``room`` (:func:`bench_room`), ``viewer_stream``
        (:func:`bench_viewer_stream`), ``gain_advice`` (:func:`bench_gain_advice`) and ``fem``
        (:func:`bench_fem`) added. Prints nothing (``haptic bench``
        prints it once, as JSON).
    """
    result = bench_world()
    result["room"] = bench_room()
    result["fem"] = bench_fem()
    result["viewer_stream"] = bench_viewer_stream()
    result["gain_advice"] = bench_gain_advice()
    return result


def run(json_out: bool) -> dict[str, Any]:
    """Run the default benchmark (about 1-2 minutes) and print JSON or a short table.

    Parameters
    ----------
    json_out : bool
        Print the result as JSON (True) or as a human-readable table (False).

    Returns
    -------
    dict
        The :func:`bench_world` result.
    """
    result = measure()
    stream, advice, room = result["viewer_stream"], result["gain_advice"], result["room"]
    if json_out:
        print(json.dumps(result, indent=2))
    else:
        for mesh in result["meshes"]:
            print(f"{mesh['n_vertices']:>6} vertices: build {mesh['build_s']:.2f} s")
            for r in mesh["runs"]:
                print(
                    f"    {r['users']:>3} users: median {r['median_ms']:.2f} ms, "
                    f"p99 {r['p99_ms']:.2f} ms, CPU median {r['cpu_median_ms']:.2f} ms, "
                    f"{r['solves_per_tick']:.2f} solves/tick "
                    f"(closest point every tick: median {r['closest_median_ms']:.2f} ms)"
                )
        print(
            f"room tick, {room['users']} users and {room['viewers']} viewers at "
            f"{room['n_vertices']} vertices: CPU median {room['tick_cpu_ms_p50']:.2f} ms (world "
            f"{room['world_cpu_ms_p50']:.2f}, gains {room['gains_cpu_ms_p50']:.2f}), p99 "
            f"{room['tick_cpu_ms_p99']:.2f} ms; wall median {room['tick_ms_p50']:.2f} ms"
        )
        for row in result["fem"]["meshes"]:
            print(
                f"FEM {row['n_vertices']:>6} vertices, {row['nodes']} nodes: volume mesh "
                f"{row['volume_mesh_s']:.1f} s, factor {row['factor_s']:.1f} s, modes "
                f"{row['modes_s']:.1f} s; {row['users']} users: median {row['median_ms']:.2f} ms, "
                f"p99 {row['p99_ms']:.2f} ms"
            )
        print(
            f"viewer bytes/s at {stream['n_vertices']} vertices, {stream['sim_rate_hz']:g} Hz, "
            f"a {stream['dent_m'] * 1e3:.1f} mm press (payload / on the wire, kB/s):"
        )
        for name, r in [*stream["phases"].items(), ("press+hold+release", stream["press"])]:
            print(
                f"    {name:>18}: float32 {r['float32_bytes_per_s'] / 1e3:7.1f} / "
                f"{r['float32_wire_bytes_per_s'] / 1e3:7.1f}   stream "
                f"{r['stream_bytes_per_s'] / 1e3:6.1f} / {r['stream_wire_bytes_per_s'] / 1e3:6.1f}"
                f"   max error {r['max_error_m'] * 1e3:.3f} mm"
            )
        print(
            f"recommended gains: {advice['hit_us_p50']:.1f} us per user per tick (p99 "
            f"{advice['hit_us_p99']:.1f}), {advice['per_tick_us_p50_at_users']:.0f} us per tick "
            f"at {advice['users']} users; a missing cell {advice['miss_us_p50']:.1f} us"
        )
    return result


if __name__ == "__main__":
    run(json_out=False)
