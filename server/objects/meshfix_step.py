"""The MeshFix step of ``--mesh-repair``, run as its own process: ``python meshfix_step.py``.

MeshFix (Attene 2010) and its Python binding ``pymeshfix`` are licensed under the AGPL. As with
TetGen (:mod:`server.objects.tetgen_step`), the server never imports this module or
``pymeshfix``: :func:`server.objects.repair.meshfix` runs this file in a child process, and only
for an open piece of a mesh given with ``--mesh-repair``.

Usage: ``python meshfix_step.py IN.npz OUT.npz`` (it needs only numpy and pymeshfix), where IN
holds ``vertices`` (n, 3) float64 and ``faces`` (m, 3) int64 of one piece; OUT gets the repaired
``vertices`` and ``faces``: holes filled, self-intersections and non-manifold elements removed,
only the largest connected part kept (``MeshFix.repair`` with its defaults). Exit status 0 on
success, 2 with one line on stderr when pymeshfix is missing or fails.

Reference: Attene, M. (2010). A lightweight approach to repairing digitized polygon meshes.
*The Visual Computer* 26(11), 1393-1406.
"""

from __future__ import annotations

import sys

import numpy as np


def main(argv: list[str]) -> int:
    """Repair IN into OUT (module docstring); the exit status."""
    if len(argv) != 2:
        print("usage: meshfix_step IN.npz OUT.npz", file=sys.stderr)
        return 2
    src, dst = argv
    try:
        import pymeshfix
    except ImportError:
        print(
            "the 'pymeshfix' package is not installed (pip install pymeshfix: AGPL, run in a "
            "child process)",
            file=sys.stderr,
        )
        return 2
    with np.load(src) as data:
        vertices = np.asarray(data["vertices"], dtype=np.float64)
        faces = np.asarray(data["faces"], dtype=np.int32)
    try:
        fix = pymeshfix.MeshFix(vertices, faces)
        fix.repair(joincomp=False, remove_smallest_components=True)
    except Exception as exc:  # MeshFix reports what it cannot mend this way
        print(f"MeshFix failed: {exc}", file=sys.stderr)
        return 2
    np.savez(
        dst,
        vertices=np.asarray(fix.points, dtype=np.float64),
        faces=np.asarray(fix.faces, dtype=np.int64),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
