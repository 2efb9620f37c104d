"""K_o, modes and cost of the FEM solid's linear elements, plain (P1) against averaged nodal pressure.

Every mesh too large for quadratic elements (``P2_MAX_NODES``) is built with linear tetrahedra;
since 2026-11-28 with averaged nodal pressure (``FemParams(element="anp")``, Bonet and Burton
1998), before plain P1. This builds each of the stress shapes (:data:`server.objects.shapes.
STRESS_MESHES`) and the 2562-vertex sphere both ways, alternating, at the liver preset's E and
each ``--nu``, with the default modes and one BLAS thread, and records K_o at the top and side
as the server logs it, the lowest three natural frequencies, the factor's non-zeros, the
start-up's steps and the median of 10 patch solves (a cache miss each) at spread centres.
JSON to ``--json``; a table to stdout.

Usage: ``PYTHONPATH=. python tools/fem_anp_cost.py --json docs/results/fem-anp-...json``
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from dataclasses import replace
from typing import Any

import trimesh

from haptic_collab.bench.world import single_thread_blas
from haptic_collab.server.materials import top_side_stiffness
from haptic_collab.server.objects.fem import FemParams, FemSolid
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.objects.shapes import STRESS_MESHES, stress_mesh
from haptic_collab.server.solid_materials import SOLID_PRESETS, solid_to_params
from tools.fem_p2_cost import patch_solves_ms


def surfaces(names: list[str]) -> dict[str, trimesh.Trimesh]:
    out = {}
    for name in names:
        out[name] = default_balloon(0.1, 4) if name == "sphere" else stress_mesh(name)
    return out


def measure(surface: trimesh.Trimesh, params: FemParams, cache: str) -> dict[str, Any]:
    start = time.perf_counter()
    solid = FemSolid(surface, params, cache_dir=cache)
    startup = time.perf_counter() - start
    solves = patch_solves_ms(solid, count=10)
    top, side = top_side_stiffness(solid)
    return {
        "element": solid.element,
        "surface_vertices": solid.n_vertices,
        "nodes": len(solid.nodes),
        "k_o_top_n_m": round(top, 1),
        "k_o_side_n_m": round(side, 1),
        "lowest_hz": [round(float(f), 3) for f in solid.natural_frequencies_hz[:3]],
        "modes": len(solid.natural_frequencies_hz),
        "factor_nnz": solid.factor_nnz,
        "startup_s": round(startup, 2),
        **{k: round(v, 2) for k, v in solid.timings.items()},
        "patch_solve_ms": round(statistics.median(solves), 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="sphere," + ",".join(STRESS_MESHES))
    ap.add_argument("--nu", default="0.45,0.49")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    base = solid_to_params(SOLID_PRESETS["liver"], FemParams())
    rows = []
    with single_thread_blas(), tempfile.TemporaryDirectory() as cache:
        for name, surface in surfaces(args.only.split(",")).items():
            for nu in (float(x) for x in args.nu.split(",")):
                for element in ("p1", "anp"):
                    params = replace(base, poisson=nu, element=element)
                    row = {"mesh": name, "poisson": nu, **measure(surface, params, cache)}
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    out = {
        "date": time.strftime("%Y-%m-%d"),
        "what": __doc__.splitlines()[0],
        "material": "liver preset (E, density, damping), nu as given",
        "rows": rows,
    }
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
