"""The FEM solid under its own weight (``haptic server --object fem --gravity``): sag and start-up.

For each object (a mesh and a solid material) the server's own build path
(:func:`server.main.build_world`) is run with and without gravity, alternately, ``repeats`` times
each, on one warmed volume-mesh cache (TetGen is not timed): the start-up time [s] of each (its
median and the ratio of the medians), the solve of the weight alone (``gravity_s``), and the sag
[mm]: at the top centre, the largest, and the largest as a share of the object's height.

Run: ``python -m haptic_collab.bench.fem_gravity --json FILE`` (docs/fem.md, "Gravity").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Any

import numpy as np

#: (mesh, material) of each object measured: the default liver sphere, Ecoflex on the sphere
#: and on the stress set's box.
CASES: tuple[tuple[str, str], ...] = (
    ("balloon", "liver"),
    ("balloon", "ecoflex-0030"),
    ("box", "ecoflex-0030"),
)


def _build(mesh: str, material: str, g: float, cache: str, subdivisions: int) -> tuple[float, Any]:
    """One server start-up of the object [s] and the object built."""
    from haptic_collab.server.main import ServerOptions, build_world

    opts = ServerOptions(
        object="fem",
        mesh=mesh,
        material=material,
        gravity_m_s2=g,
        volume_cache=cache,
        subdivisions=subdivisions,
    )
    clock = time.perf_counter()
    world = build_world(opts)
    return time.perf_counter() - clock, world.obj


def _sag(obj: Any) -> dict[str, float]:
    """The sag of a built solid: at the top centre, the largest, its share of the height."""
    mesh = np.asarray(obj.mesh_vertices)
    lo, hi = mesh.min(axis=0), mesh.max(axis=0)
    centre = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, hi[2]])
    top = int(np.argmin(np.linalg.norm(mesh - centre, axis=1)))
    height = float(np.ptp(obj.nodes[:, 2]))
    return {
        "sag_top_mm": -1e3 * float(obj.sag[top, 2]),
        "sag_max_mm": 1e3 * float(obj.sag_m),
        "sag_share_of_height": float(obj.sag_m) / height,
        "height_mm": 1e3 * height,
        "weight_n": float(obj.mass_kg) * float(obj.params.gravity_m_s2),
    }


def bench_fem_gravity(
    g: float = 9.81,
    repeats: int = 3,
    cases: Sequence[tuple[str, str]] = CASES,
    subdivisions: int = 4,
) -> dict[str, Any]:
    """Sag and start-up time of the FEM solid with and without gravity (module docstring).

    Parameters
    ----------
    g : float
        Gravity [m/s^2] of the runs with it.
    repeats : int
        Builds of each object with and without gravity, alternating (>= 1).
    cases : sequence of (mesh, material)
    subdivisions : int
        Of the ``balloon`` sphere (4, the server's default: 2562 vertices).

    Returns
    -------
    dict
        JSON-able: ``{"benchmark": "fem-gravity", "g_m_s2", "repeats", "objects": [{"mesh",
        "material", "n_vertices", "nodes", "tetrahedra", "mass_kg", "sag_top_mm", "sag_max_mm",
        "sag_share_of_height", "height_mm", "weight_n", "startup_s": {"without": [...],
        "with": [...]}, "startup_median_s": {...}, "startup_ratio", "gravity_solve_median_s",
        "k_o_top_n_m": {"without", "with"}}]}``.
    """
    from haptic_collab.bench.world import single_thread_blas
    from haptic_collab.server.materials import top_side_stiffness

    objects = []
    with single_thread_blas() as limited, tempfile.TemporaryDirectory() as cache:
        for mesh, material in cases:
            _build(
                mesh, material, 0.0, cache, subdivisions
            )  # the volume mesh into the cache: TetGen untimed
            times: dict[str, list[float]] = {"without": [], "with": []}
            solves: list[float] = []
            built: dict[str, Any] = {}
            for _ in range(repeats):
                for name, gee in (("without", 0.0), ("with", g)):
                    seconds, obj = _build(mesh, material, gee, cache, subdivisions)
                    times[name].append(seconds)
                    if gee > 0.0:
                        solves.append(obj.timings["gravity_s"])
                    built[name] = obj
            med = {k: statistics.median(v) for k, v in times.items()}
            obj = built["with"]
            objects.append(
                {
                    "mesh": mesh,
                    "material": material,
                    "n_vertices": int(obj.n_vertices),
                    "nodes": len(obj.nodes),
                    "tetrahedra": len(obj.tets),
                    "mass_kg": float(obj.mass_kg),
                    **_sag(obj),
                    "startup_s": times,
                    "startup_median_s": med,
                    "startup_ratio": med["with"] / med["without"],
                    "gravity_solve_median_s": statistics.median(solves),
                    "k_o_top_n_m": {
                        k: float(top_side_stiffness(built[k])[0]) for k in ("without", "with")
                    },
                }
            )
    return {
        "benchmark": "fem-gravity",
        "g_m_s2": g,
        "repeats": repeats,
        "subdivisions": subdivisions,
        "blas_libraries_single_threaded": limited,
        "objects": objects,
    }


def _commit() -> str:
    """The checkout's commit (with ``+dirty`` when it has uncommitted changes), or ''."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "."], cwd=here, capture_output=True, text=True
        ).stdout.strip()
    except OSError:
        return ""
    return head + ("+dirty" if dirty else "")


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m haptic_collab.bench.fem_gravity [--g G] [--repeats R] [--json FILE]``."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--g", type=float, default=9.81, help="gravity [m/s^2] (default 9.81)")
    p.add_argument("--repeats", type=int, default=3, help="builds of each, alternating")
    p.add_argument("--json", default=None, help="write the result here (default: stdout)")
    args = p.parse_args(argv)
    started = datetime.now(UTC)
    result = {
        "command": "python -m haptic_collab.bench.fem_gravity "
        + " ".join(argv if argv is not None else sys.argv[1:]),
        "commit": _commit(),
        "started_utc": started.isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "load_average_at_start": list(os.getloadavg()),
        },
        **bench_fem_gravity(args.g, args.repeats),
    }
    result["machine"]["load_average_at_end"] = list(os.getloadavg())
    text = json.dumps(result, indent=2)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
