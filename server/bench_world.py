"""Benchmark of the simulation core: per-tick cost of :meth:`server.world.World.tick`.

For each mesh size the default balloon is built (operators, ordering, one factorization: timed as
``build_s``), then for each number of users a fresh run of ticks is timed. Users are spread over
the balloon (not on the fixed base), press 2-5 mm in with a proportional local model
``f = K_h * e`` (``K_h = 0.5 K_o_eff`` from the last output, section 6 Step 2), and their probes
drift about 0.3 mm per tick along the surface with 0.1 mm jitter, so that the patch cache sees
the misses a slowly moving hand causes. The first ``warmup`` ticks (every patch solved for the
first time) are reported apart as ``first_tick_ms``.

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

from server.objects.balloon import Balloon, BalloonParams
from server.objects.mesh import default_balloon
from server.world import ContactInput, World

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


def _run_users(world: World, users: int, ticks: int, warmup: int, seed: int) -> dict[str, Any]:
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
    for _ in range(warmup + ticks):
        dirs = dirs + (3e-4 / radius) * drift + rng.normal(0.0, 1e-4 / radius, dirs.shape)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        dirs[:, 2] = np.maximum(dirs[:, 2], -0.6)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        probes = centre + dirs * (radius - depth[:, None])
        inputs = {n: ContactInput(probe=probes[i], force=forces[i]) for i, n in enumerate(names)}
        start = time.perf_counter()
        out = world.tick(inputs)
        times_ms.append((time.perf_counter() - start) * 1e3)
        for i, n in enumerate(names):
            o = out[n]
            if gains[i] == 0.0:
                gains[i] = 0.5 * o.k_o_eff
            forces[i] = gains[i] * max(o.penetration_m, 0.0) * o.normal
    steady = np.asarray(times_ms[warmup:])
    return {
        "users": users,
        "ticks": ticks,
        "median_ms": float(np.median(steady)),
        "p99_ms": float(np.percentile(steady, 99)),
        "max_ms": float(np.max(steady)),
        "first_tick_ms": float(times_ms[0]),
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
        "median_ms", "p99_ms", "max_ms", "first_tick_ms", "solves_per_tick"}]}], ...}``.

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
        world = World(obj)
        solves_before = obj.solve_count
        result = _run_users(world, users, _ticks_for(n, ticks), warmup, seed)
        result["solves_per_tick"] = (obj.solve_count - solves_before) / (warmup + result["ticks"])
        runs.append(result)
    return {"n_vertices": n, "build_s": build_s, "runs": runs}


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
    result = bench_world()
    if json_out:
        print(json.dumps(result, indent=2))
    else:
        for mesh in result["meshes"]:
            print(f"{mesh['n_vertices']:>6} vertices: build {mesh['build_s']:.2f} s")
            for r in mesh["runs"]:
                print(
                    f"    {r['users']:>3} users: median {r['median_ms']:.2f} ms, "
                    f"p99 {r['p99_ms']:.2f} ms, {r['solves_per_tick']:.2f} solves/tick"
                )
    return result


if __name__ == "__main__":
    run(json_out=False)
