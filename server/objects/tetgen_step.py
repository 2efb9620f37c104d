"""The TetGen step, run as its own process: ``python .../server/objects/tetgen_step.py``.

TetGen (Si 2015) is licensed under the AGPL; its Python wrapper (the ``tetgen`` package, MIT,
installed by the ``fem`` extra) links it. The server never imports this module or ``tetgen``:
:func:`server.objects.volume.volume_mesh` runs this file in a child process, once per surface,
and caches the volume mesh it writes (docs/fem.md).

Usage: ``python tetgen_step.py IN.npz OUT.npz SWITCHES`` (it needs only numpy and tetgen), where
IN holds ``vertices`` (n, 3) float64 [m] and ``faces`` (m, 3) int64; OUT gets ``nodes`` (N, 3)
float64 [m] (the n surface vertices first, unchanged: switch ``Y``) and ``tets`` (T, 4) int64.
Exit status 0 on success, 2 with one line on stderr when TetGen is missing or fails.

Reference: Si, H. (2015). TetGen, a Delaunay-based quality tetrahedral mesh generator. *ACM
Transactions on Mathematical Software* 41(2), 11.
"""

from __future__ import annotations

import sys

import numpy as np


def main(argv: list[str]) -> int:
    """Tetrahedralise IN into OUT (module docstring); the exit status."""
    if len(argv) != 3:
        print("usage: tetgen_step IN.npz OUT.npz SWITCHES", file=sys.stderr)
        return 2
    src, dst, switches = argv
    try:
        import tetgen
    except ImportError:
        print("the 'tetgen' package is not installed", file=sys.stderr)
        return 2
    with np.load(src) as data:
        vertices = np.asarray(data["vertices"], dtype=np.float64)
        faces = np.asarray(data["faces"], dtype=np.int64)
    try:
        out = tetgen.TetGen(vertices, faces).tetrahedralize(switches=switches)
    except Exception as exc:  # TetGen reports a self-intersecting or open surface this way
        print(f"TetGen failed: {exc}", file=sys.stderr)
        return 2
    nodes, tets = np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)
    np.savez(dst, nodes=nodes, tets=tets)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
