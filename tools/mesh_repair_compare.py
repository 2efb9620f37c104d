"""Compare mesh repair libraries on the project's broken meshes and on built CAD-like parts.

Not installed, not a test: the measurement behind the choice of ``--mesh-repair``'s library
(docs/real-objects.md). For each case and each candidate: whether the result passes the
server's checks (:func:`server.objects.mesh.repair_mesh`), its enclosed volume against the
intended one, how far the repaired surface strays from the input (the largest distance from a
repaired vertex to the input surface, as a fraction of the object's size), and the time.

Usage (from the repository, after ``make install meshes``)::

    .venv/bin/python tools/mesh_repair_compare.py --out docs/results/mesh-repair-DATE.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
MESHES = ROOT / "tests" / "data" / "meshes"


def cases() -> list[tuple[str, trimesh.Trimesh, float | None]]:
    """(label, mesh, intended volume [m^3] or None) of every case."""
    from tests.server.test_mesh_repair import (
        box_with_a_hole,
        box_with_duplicated_faces_and_a_fin,
        overlapping_boxes,
        two_boxes_sharing_an_edge,
    )

    out: list[tuple[str, trimesh.Trimesh, float | None]] = [
        ("box with a hole (open)", box_with_a_hole(), 0.1**3),
        ("two boxes sharing an edge (non-manifold edge)", two_boxes_sharing_an_edge(), 2e-3),
        ("two overlapping boxes (self-intersecting, 2 bodies)", overlapping_boxes(), 0.1**3 * 1.5),
        ("box with duplicated faces and a fin", box_with_duplicated_faces_and_a_fin(), 0.1**3),
    ]
    for name, label in (
        ("ant.ply", "pyvista ant (15 intersecting bodies)"),
        ("StanfordBunny.ply", "pymeshfix Stanford bunny scan (open, non-manifold)"),
        ("bunny.obj", "npm bunny (valid: a repair should not change it)"),
    ):
        if (MESHES / name).is_file():
            loaded = trimesh.load(MESHES / name, process=False)
            assert isinstance(loaded, trimesh.Trimesh)
            out.append((label, loaded, None))
    return out


def candidates() -> dict[str, Callable[[trimesh.Trimesh], trimesh.Trimesh]]:
    from haptic_collab.server.objects import repair

    return {
        "pymeshfix": repair.repair_pymeshfix,
        "manifold3d": repair.repair_manifold3d,
        "trimesh": repair.repair_trimesh,
        "chosen (repair_mesh_topology)": lambda m: repair.repair_mesh_topology(m)[0],
    }


def measure(label: str, mesh: trimesh.Trimesh, volume: float | None, name: str, fn) -> dict:  # type: ignore[no-untyped-def]
    from haptic_collab.server.objects.mesh import MeshError, repair_mesh

    row: dict = {"case": label, "library": name}
    start = time.perf_counter()
    try:
        out = fn(mesh)
    except Exception as exc:  # a library that gives up is a result, not a crash
        row["error"] = f"{type(exc).__name__}: {exc}"[:200]
        return row
    row["ms"] = round((time.perf_counter() - start) * 1e3, 1)
    try:
        ok = repair_mesh(out, label)
        row["accepted"] = True
        row["volume"] = float(ok.volume)
    except MeshError as exc:
        row["accepted"] = False
        row["refused"] = str(exc).split(": ", 1)[1][:160]
    row["vertices_in_out"] = [len(mesh.vertices), len(out.vertices)]
    if volume is not None and row.get("accepted"):
        row["volume_error"] = round(row["volume"] / volume - 1.0, 4)
    size = float(np.max(mesh.extents))
    if len(out.vertices):
        # the input surface sampled densely (trimesh's exact closest point needs rtree)
        dense, _ = trimesh.sample.sample_surface(mesh, 200_000, seed=1)
        dist, _ = cKDTree(np.vstack([dense, mesh.vertices])).query(np.asarray(out.vertices))
        row["max_deviation_of_size"] = round(float(np.max(dist)) / size, 4)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    opts = ap.parse_args()
    rows = []
    for label, mesh, volume in cases():
        for name, fn in candidates().items():
            row = measure(label, mesh, volume, name, fn)
            print(json.dumps(row), flush=True)
            rows.append(row)
    result = {
        "rows": rows,
        "date": time.strftime("%Y-%m-%d"),
        "commit": subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
        ).stdout.strip(),
        "command": "tools/mesh_repair_compare.py " + " ".join(sys.argv[1:]),
    }
    if opts.out is not None:
        opts.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
