"""A tetrahedral volume mesh of a closed surface that keeps the surface's vertices (docs/fem.md).

The FEM solid (:mod:`server.objects.fem`) needs tetrahedra whose first ``n`` nodes are the
surface mesh's ``n`` vertices, unchanged and in order, so the surface, its patches and the
viewer's indices stay as they are. TetGen builds them (switches ``p`` a piecewise linear
complex, ``Y`` no Steiner point on the surface, ``q`` a quality bound, ``Q`` quiet).

Licence: TetGen is AGPL. It is an optional extra (``fem``: :func:`shared.extras.install_hint`) and runs
as a separate process (:mod:`server.objects.tetgen_step`), never imported by the server; its
output, a plain array file, is cached per surface under ``cache_dir`` (default
``$XDG_CACHE_HOME/haptic-collab/volumes``, or ``~/.cache/...``). A cached volume mesh is used
without TetGen installed. A crash of TetGen (it aborts on some self-intersecting surfaces) is a
failed step, not a failed server.

Every volume mesh, fresh or cached, is checked before use (:func:`check_volume_mesh`). A cached
one is also verified whole: the file carries a sha256 of its nodes and tetrahedra
(:func:`volume_digest`), and a file whose arrays do not match it (an interior node moved, a
tetrahedron changed, or a file from before the hash) is logged and rebuilt, never used. The
surface check alone cannot see an interior node moved (issue 60: one moved 0.5 m made the liver
ball 20 % stiffer).

Nothing here uses threads, sockets or clocks; it writes files and runs one child process.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import numpy.typing as npt

from haptic_collab.server.objects.mesh import MeshError
from haptic_collab.shared.extras import install_hint
from haptic_collab.shared.types import FloatArray, IntArray

log = logging.getLogger(__name__)

#: TetGen switches: PLC input, no Steiner points on the surface, radius-edge ratio <= 1.5 and
#: dihedral angles >= 15 degrees, quiet.
TETGEN_SWITCHES = "pq1.5/15YQ"


def tetgen_switches(max_edge_m: float | None = None) -> str:
    """TetGen's switches: :data:`TETGEN_SWITCHES`, and with ``max_edge_m`` [m] a volume limit
    (switch ``a``): no tetrahedron larger than the regular one of that edge, ``e^3 / (6 sqrt 2)``.

    Raises
    ------
    ValueError
        ``max_edge_m`` not finite and > 0.
    """
    if max_edge_m is None:
        return TETGEN_SWITCHES
    e = float(max_edge_m)
    if not (math.isfinite(e) and e > 0.0):
        raise ValueError(f"the largest tetrahedron's edge must be > 0 m, got {max_edge_m!r}")
    return TETGEN_SWITCHES.replace("YQ", f"Ya{e**3 / (6.0 * math.sqrt(2.0)):.6e}Q")


#: Seconds TetGen may take (about 14 s for a 41k-vertex sphere on this project's CI machine).
TETGEN_TIMEOUT_S = 600.0

#: A tetrahedron whose volume is below this share of the mean edge length cubed is degenerate.
_DEGENERATE = 1e-9


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/haptic-collab/volumes`` (``~/.cache`` when unset)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "haptic-collab" / "volumes"


def surface_digest(vertices: npt.ArrayLike, faces: npt.ArrayLike, switches: str) -> str:
    """A name for the volume mesh of this exact surface and switches (sha256, 24 hex digits)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(faces, dtype=np.int64).tobytes())
    h.update(switches.encode())
    return h.hexdigest()[:24]


def volume_digest(nodes: npt.ArrayLike, tets: npt.ArrayLike) -> str:
    """The sha256 (hex) of a volume mesh's nodes (float64 [m]) and tetrahedra (int64), shapes
    included: what a cached volume mesh is verified against before use."""
    p = np.ascontiguousarray(nodes, dtype=np.float64)
    t = np.ascontiguousarray(tets, dtype=np.int64)
    h = hashlib.sha256()
    h.update(repr((p.shape, t.shape)).encode())
    h.update(p.tobytes())
    h.update(t.tobytes())
    return h.hexdigest()


def _load_cached(path: Path, surface: FloatArray) -> tuple[FloatArray, IntArray] | None:
    """The cached volume mesh at ``path`` if it is whole and fits ``surface``, else None (the
    file is deleted and the reason logged, so the caller rebuilds it)."""
    try:
        with np.load(path) as data:
            nodes, tets = np.asarray(data["nodes"]), np.asarray(data["tets"])
            stored = str(data["digest"]) if "digest" in data.files else None
        if stored != volume_digest(nodes, tets):
            why = "it has no hash" if stored is None else "its nodes or tetrahedra do not match it"
            log.warning("cached volume mesh %s refused: %s; rebuilding it", path, why)
            path.unlink(missing_ok=True)
            return None
        return check_volume_mesh(nodes, tets, surface)
    except (OSError, KeyError, ValueError) as exc:  # MeshError is a ValueError
        log.warning("cached volume mesh %s refused (%s); rebuilding it", path, exc)
        path.unlink(missing_ok=True)
        return None


def check_volume_mesh(
    nodes: npt.ArrayLike, tets: npt.ArrayLike, surface_vertices: npt.ArrayLike
) -> tuple[FloatArray, IntArray]:
    """Check a volume mesh against its surface; its tetrahedra positively oriented.

    Parameters
    ----------
    nodes : (N, 3) float [m]
    tets : (T, 4) int, node indices.
    surface_vertices : (n, 3) float [m], which must be ``nodes[:n]`` exactly.

    Returns
    -------
    (nodes (N, 3) float64, tets (T, 4) int64)
        Tetrahedra reordered where needed so each has a positive volume.

    Raises
    ------
    MeshError
        Non-finite nodes, an index out of range, surface vertices moved or missing, a node in no
        tetrahedron, or a degenerate tetrahedron (volume below 1e-9 of its mean edge cubed).
    """
    p = np.asarray(nodes, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64)
    s = np.asarray(surface_vertices, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise MeshError("volume mesh: nodes must be finite (N, 3) coordinates")
    if t.ndim != 2 or t.shape[1] != 4 or len(t) == 0:
        raise MeshError("volume mesh: no tetrahedra")
    if t.min() < 0 or t.max() >= len(p):
        raise MeshError("volume mesh: a tetrahedron names a node that does not exist")
    if len(p) < len(s) or not np.array_equal(p[: len(s)], s):
        raise MeshError("volume mesh: the surface vertices are not its first nodes, unchanged")
    if np.bincount(t.ravel(), minlength=len(p)).min() == 0:
        raise MeshError("volume mesh: a node belongs to no tetrahedron")
    x = p[t]
    e1, e2, e3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    vol = np.einsum("ij,ij->i", np.cross(e1, e2), e3) / 6.0
    edges = np.stack([e1, e2, e3, x[:, 2] - x[:, 1], x[:, 3] - x[:, 1], x[:, 3] - x[:, 2]], axis=1)
    mean_edge = np.linalg.norm(edges, axis=2).mean(axis=1)
    bad = np.abs(vol) <= _DEGENERATE * mean_edge**3
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeshError(
            f"volume mesh: {int(bad.sum())} degenerate tetrahedra (the first, #{i}, has volume "
            f"{vol[i]:.3g} m^3)"
        )
    flip = vol < 0.0
    if flip.any():
        t = t.copy()
        t[flip] = t[flip][:, [0, 2, 1, 3]]
    return p, t


def volume_mesh(
    vertices: npt.ArrayLike,
    faces: npt.ArrayLike,
    cache_dir: str | Path | None = None,
    switches: str = TETGEN_SWITCHES,
    timeout_s: float = TETGEN_TIMEOUT_S,
) -> tuple[FloatArray, IntArray]:
    """The checked volume mesh of a closed surface, from the cache or from TetGen.

    Parameters
    ----------
    vertices : (n, 3) float [m]; faces : (m, 3) int
        A closed, outward-wound surface (:func:`server.objects.mesh.load_mesh` checks one).
    cache_dir : path, optional
        Where volume meshes are kept (:func:`default_cache_dir`).
    switches : str
        TetGen's switches; ``Y`` must stay (surface vertices unchanged).
    timeout_s : float
        Longest TetGen run [s].

    Returns
    -------
    (nodes (N, 3) float64 [m], tets (T, 4) int64)
        ``nodes[:n]`` are ``vertices``.

    Raises
    ------
    MeshError
        TetGen not installed and no whole cached mesh (one that fails its hash or the checks
        is logged and rebuilt); TetGen failed, crashed or timed out (a self-
        intersecting surface); its output fails :func:`check_volume_mesh`.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    folder = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    cached = folder / f"{surface_digest(v, f, switches)}.npz"
    if cached.is_file():
        found = _load_cached(cached, v)
        if found is not None:
            return found
    with tempfile.TemporaryDirectory(prefix="haptic-tet-") as tmp:
        src, dst = Path(tmp) / "surface.npz", Path(tmp) / "volume.npz"
        np.savez(src, vertices=v, faces=f)
        cmd = [sys.executable, str(Path(__file__).with_name("tetgen_step.py"))]
        try:
            done = subprocess.run(
                [*cmd, str(src), str(dst), switches],
                capture_output=True,
                text=True,
                timeout=timeout_s,
                check=False,
                cwd=tmp,  # TetGen writes tetgen-tmpfile_skipped.* into the cwd when it fails
            )
        except subprocess.TimeoutExpired as exc:
            raise MeshError(f"TetGen did not finish within {timeout_s:g} s") from exc
        if done.returncode != 0 or not dst.is_file():
            lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
            why = lines[-1] if lines else f"exit status {done.returncode}"
            if "not installed" in why:
                raise MeshError(
                    "the FEM object needs a volume mesh and TetGen is not installed: "
                    f"{install_hint('fem')}; TetGen is AGPL and runs as a separate "
                    "step (docs/fem.md)"
                )
            raise MeshError(
                f"the surface could not be tetrahedralised ({why}); is it self-intersecting?"
            )
        with np.load(dst) as data:
            nodes, tets = check_volume_mesh(data["nodes"], data["tets"], v)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        partial = cached.with_suffix(".tmp.npz")
        np.savez(partial, nodes=nodes, tets=tets, digest=volume_digest(nodes, tets))
        partial.replace(cached)
    except OSError:
        pass  # no writable cache: the mesh is rebuilt next time
    return nodes, tets
