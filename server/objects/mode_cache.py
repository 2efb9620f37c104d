"""A disk cache of a FEM solid's modes: the second start of the same solid skips the eigensolve.

The modes are most of a FEM solid's start-up (docs/fem.md, "Cost of the quadratic elements":
13 of the default liver sphere's 15 s, 20 of the palpation solid's 24 s), and a server, a
demo or a room started again builds the same solid. :class:`server.objects.fem.FemSolid` keeps
its modes here, beside the cached volume meshes (``--volume-cache``).

- **The key** is a sha256 of everything the eigenproblem is made of: the free stiffness matrix
  (its shape, sparsity and values, in the solid's own row order), the lumped masses, how many
  modes at most, the settle frequency and :data:`MODES_FORMAT`. A change to the mesh, a
  material, the base, the rates or the solver's rules is another key.
- **Verified before use**, not trusted: every cached mode must satisfy ``K phi = w^2 M phi`` to
  :data:`RESIDUAL_TOL` of ``|K phi|`` and be mass-normalised (``phi^T M phi = I`` to
  :data:`ORTHO_TOL`). A file that fails (truncated, edited, from another machine's bug) is
  logged, deleted and the modes are solved again. The check costs two sparse products.
- **Bounded**: after a write the oldest mode files (by last use) are deleted until those left
  take at most :data:`CACHE_MB` MB. A folder that cannot be written only costs the next start
  its eigensolve.

Nothing here uses sockets, threads or clocks; the files' modification times order the pruning.
"""

from __future__ import annotations

import hashlib
import logging
import os
import zipfile
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from haptic_collab.shared.types import FloatArray

log = logging.getLogger(__name__)

#: Changes when the way modes are chosen or stored changes: older files are other keys.
MODES_FORMAT = "fem-modes-v1"

#: Largest ``|K phi - w^2 M phi| / |K phi|`` of a cached mode accepted (ARPACK's are ~1e-12).
RESIDUAL_TOL = 1e-7

#: Largest ``|phi^T M phi - I|`` entry of cached modes accepted.
ORTHO_TOL = 1e-7

#: The mode files kept together at most [MB] (the default sphere's are about 22 MB).
CACHE_MB = 512.0

#: File names of cached modes: ``modes-<key>.npz``.
_PREFIX = "modes-"


def modes_key(k_free: sp.spmatrix, m_rows: npt.ArrayLike, count: int, omega_c: float) -> str:
    """The cache key (sha256, 32 hex digits) of the eigenproblem ``K phi = w^2 M phi`` with
    ``k_free`` (the free stiffness, any sparse format), the lumped masses ``m_rows`` [kg] of its
    rows, at most ``count`` modes and the settle frequency ``omega_c`` [rad/s]."""
    k = sp.csc_matrix(k_free)
    if not k.has_sorted_indices:
        k = k.sorted_indices()  # a copy: the caller's matrix is left as it is
    h = hashlib.sha256()
    h.update(MODES_FORMAT.encode())
    h.update(repr((k.shape, int(count), float(omega_c).hex())).encode())
    h.update(np.ascontiguousarray(k.indptr, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(k.indices, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(k.data, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(m_rows, dtype=np.float64).tobytes())
    return h.hexdigest()[:32]


def _path(folder: str | Path, key: str) -> Path:
    return Path(folder) / f"{_PREFIX}{key}.npz"


def _verified(
    vals: FloatArray, phi: FloatArray, k_free: sp.spmatrix, m_rows: FloatArray
) -> str | None:
    """Why the modes ``(vals (m,) [rad^2/s^2], phi (rows, m))`` do not solve the problem, or
    None when they do."""
    rows = k_free.shape[0]
    if phi.ndim != 2 or phi.shape[0] != rows or vals.shape != (phi.shape[1],):
        return f"shapes {phi.shape} and {vals.shape} do not fit {rows} rows"
    if not (np.all(np.isfinite(vals)) and np.all(np.isfinite(phi))):
        return "it holds a non-finite number"
    if vals.size and (np.any(vals <= 0.0) or np.any(np.diff(vals) < 0.0)):
        return "its frequencies are not positive and ascending"
    kphi = np.asarray(k_free @ phi)
    residual = np.linalg.norm(kphi - (m_rows[:, None] * phi) * vals[None, :], axis=0)
    scale = np.maximum(np.linalg.norm(kphi, axis=0), np.finfo(float).tiny)
    worst = float(np.max(residual / scale)) if vals.size else 0.0
    if not worst <= RESIDUAL_TOL:
        return f"a mode misses K phi = w^2 M phi by {worst:.2g} of |K phi|"
    gram = phi.T @ (m_rows[:, None] * phi)
    off = float(np.max(np.abs(gram - np.eye(len(vals))))) if vals.size else 0.0
    if not off <= ORTHO_TOL:
        return f"the modes are not mass-orthonormal ({off:.2g})"
    return None


def load_modes(
    folder: str | Path, key: str, k_free: sp.spmatrix, m_rows: npt.ArrayLike
) -> tuple[FloatArray, FloatArray] | None:
    """The cached modes of ``key`` as ``(w^2 (m,) ascending [rad^2/s^2], phi (rows, m)
    mass-normalised)`` when a file holds them and they solve ``k_free`` and ``m_rows``'s
    problem; None otherwise (a file that fails is logged and deleted)."""
    path = _path(folder, key)
    if not path.is_file():
        return None
    m = np.ascontiguousarray(m_rows, dtype=np.float64)
    try:
        with np.load(path) as data:
            vals = np.asarray(data["omega2"], dtype=np.float64)
            phi = np.asarray(data["phi"], dtype=np.float64)
        why = _verified(vals, phi, k_free, m)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:  # truncated
        why = f"it cannot be read ({exc})"
    if why is not None:
        log.warning("cached FEM modes %s refused: %s; solving them again", path, why)
        path.unlink(missing_ok=True)
        return None
    try:
        os.utime(path)  # last used: pruned last
    except OSError:
        pass
    return vals, phi


def store_modes(folder: str | Path, key: str, omega2: FloatArray, phi: FloatArray) -> None:
    """Keep the modes of ``key`` (as :func:`load_modes` returns them), then prune the folder to
    :data:`CACHE_MB`. Never raises: a folder that cannot be written is skipped."""
    path = _path(folder, key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".tmp.npz")
        np.savez(partial, omega2=np.asarray(omega2, dtype=np.float64), phi=phi)
        partial.replace(path)
        prune(folder, keep=path)
    except OSError as exc:
        log.info("FEM modes not cached (%s): the next start solves them again", exc)


def prune(folder: str | Path, keep: Path | None = None, budget_mb: float = CACHE_MB) -> None:
    """Delete the least recently used mode files in ``folder`` until those left take at most
    ``budget_mb`` MB; ``keep`` is never deleted."""
    files = []
    for p in Path(folder).glob(f"{_PREFIX}*.npz"):
        if p.name.endswith(".tmp.npz"):  # another process's file being written
            continue
        try:
            st = p.stat()
        except OSError:
            continue
        files.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in files)
    for _, size, p in sorted(files, key=lambda f: f[0]):
        if total <= budget_mb * 1e6:
            break
        if keep is not None and p == keep:
            continue
        p.unlink(missing_ok=True)
        total -= size
