"""Start-up, tick and patch-solve cost of the FEM solid, P1 (before) and P2 (now), side by side.

The default liver sphere as ``haptic server --object fem`` builds it: P2 on the 642-vertex parent
icosphere (:func:`server.objects.fem.sphere_for_solid`, 2562 vertices shown) against P1 on the
2562-vertex icosphere (``FemParams(element="p1")``, the build before P2). Builds alternate P1 and
P2, ``--rounds`` each, with gravity on (so the sag's solve is timed) and one BLAS thread; the
volume meshes come from a cache warmed first (TetGen is timed once per element, fresh). Then
per build: one patch solve (a cache miss: the sparse solve with the factor, the modal and
rotation products) at 20 spread patch centres, and the World's tick with 8 users pressing and
drifting (``haptic bench server``'s loop, no prefetch). K_o at the top and side as the server
logs it. Medians; JSON to ``--json``.

Usage: ``PYTHONPATH=. python tools/fem_p2_cost.py --rounds 3 --json docs/results/fem-p2-...json``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from typing import Any

import numpy as np

from haptic_collab.bench.world import _run_users, single_thread_blas
from haptic_collab.server.materials import top_side_stiffness
from haptic_collab.server.objects.fem import FemParams, FemSolid, sphere_for_solid
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.objects.volume import volume_mesh
from haptic_collab.server.world import World


def build(element: str, cache: str) -> FemSolid:
    surface, chosen = sphere_for_solid(4)
    if element == "p1":
        surface, chosen = default_balloon(0.1, 4), "p1"
    return FemSolid(surface, FemParams(gravity_m_s2=9.81, element=chosen), cache_dir=cache)


def patch_solves_ms(solid: FemSolid, count: int = 20) -> list[float]:
    centres = solid._centres.centres
    keys = centres[np.linspace(0, len(centres) - 1, count).astype(int)]
    out = []
    for key in keys:
        start = time.perf_counter()
        solid._solve_patches([int(key)])
        out.append(1e3 * (time.perf_counter() - start))
    return out


def tetgen_s(element: str) -> float:
    surface, _ = sphere_for_solid(4)
    if element == "p1":
        surface = default_balloon(0.1, 4)
    with tempfile.TemporaryDirectory() as fresh:
        start = time.perf_counter()
        volume_mesh(surface.vertices, surface.faces, cache_dir=fresh)
        return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--ticks", type=int, default=100)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rows: dict[str, list[dict[str, Any]]] = {"p1": [], "p2": []}
    with single_thread_blas() as limited, tempfile.TemporaryDirectory() as cache:
        fresh = {e: tetgen_s(e) for e in ("p1", "p2")}
        for e in ("p1", "p2"):
            build(e, cache)  # warm the volume cache
        for _ in range(args.rounds):
            for element in ("p1", "p2"):
                start = time.perf_counter()
                solid = build(element, cache)
                total = time.perf_counter() - start
                top, side = top_side_stiffness(solid)  # type: ignore[arg-type]
                solves = patch_solves_ms(solid)
                solid.reset(clear_cache=True)
                ticks = _run_users(World(solid), 8, args.ticks, 3, 0)
                rows[element].append(
                    {
                        **solid.timings,
                        "start_up_s": total,
                        "patch_solve_ms": statistics.median(solves),
                        "tick_median_ms": ticks["median_ms"],
                        "tick_p99_ms": ticks["p99_ms"],
                        "k_o_top": top,
                        "k_o_side": side,
                        "nodes": len(solid.nodes),
                        "tetrahedra": len(solid.tets),
                        "dofs": len(solid._dofs),
                        "factor_nnz": solid.factor_nnz,
                        "modes": len(solid.natural_frequencies_hz),
                        "shown_vertices": solid.n_vertices,
                    }
                )
                print(element, {k: round(v, 3) for k, v in rows[element][-1].items()}, flush=True)
    keys = rows["p1"][0].keys()
    medians = {e: {k: statistics.median(r[k] for r in rows[e]) for k in keys} for e in rows}
    for e in rows:
        medians[e]["tetgen_fresh_s"] = fresh[e]
    result = {
        "what": __doc__.splitlines()[0],
        "how": " ".join(__doc__.split("\n\n")[1].split()),
        "rounds": args.rounds,
        "blas_libraries_single_threaded": limited,
        "load_average_after": os.getloadavg(),
        "median": medians,
        "runs": rows,
    }
    print(json.dumps(medians, indent=1))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=1)


if __name__ == "__main__":
    main()
