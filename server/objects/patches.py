"""Finger-pad patch centres on a closed surface: the cache keys of contact load patches.

Both deformable objects (:mod:`server.objects.balloon`, :mod:`server.objects.fem`) spread a
contact's push over a finger-pad patch around a *patch centre*, a vertex, and cache the solve of
each patch by that centre. Centres are one vertex per cubic cell of side ``spacing_m`` (the one
closest to the cell's centre) and per facing (the rest normal's dominant axis and sign), so both
sides of a part thinner than a cell, and both faces at an edge, have centres of their own.

Nothing here uses threads, sockets or clocks.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, Generic, TypeVar

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from haptic_collab.shared.types import FloatArray, IntArray

_S = TypeVar("_S")

#: A contact keeps its patch centre while within this many patch spacings of it (hysteresis).
HYSTERESIS = 0.75


class PatchCentres:
    """The patch centres of a surface and the rule that picks one for a contact.

    Parameters
    ----------
    rest : (n, 3) float [m]
        Rest vertex positions.
    normals : (n, 3) float
        Outward unit rest normals.
    spacing_m : float
        Cell side [m] (> 0): about the distance between centres.
    """

    def __init__(self, rest: FloatArray, normals: FloatArray, spacing_m: float) -> None:
        self._rest = rest
        self._normals = normals
        self._spacing = float(spacing_m)
        n = len(rest)
        s = self._spacing
        cell = np.floor((rest - rest.min(axis=0)) / s).astype(np.int64)
        cell_centre = (cell + 0.5) * s + rest.min(axis=0)
        axis = np.argmax(np.abs(normals), axis=1)
        facing = 2 * axis + (normals[np.arange(n), axis] < 0.0)
        _, cell_id = np.unique(np.column_stack([cell, facing]), axis=0, return_inverse=True)
        cell_id = cell_id.ravel()
        dist = np.linalg.norm(rest - cell_centre, axis=1)
        order = np.lexsort((dist, cell_id))
        first = np.ones(len(order), dtype=bool)
        first[1:] = cell_id[order][1:] != cell_id[order][:-1]
        self.centres: IntArray = np.sort(order[first]).astype(np.int64)
        self._tree = cKDTree(rest[self.centres])

    def key(
        self,
        point: npt.ArrayLike,
        previous: int | None = None,
        normal: npt.ArrayLike | None = None,
    ) -> int:
        """The patch centre (a vertex index) for a contact at ``point`` (3,) [m].

        With ``previous`` (the key this contact had last tick), that key is kept while the point
        stays within ``0.75 * spacing_m`` of its centre along the surface: hysteresis, so a
        contact jittering on a cell boundary does not make its load jump back and forth.

        With ``normal`` (3,), the contact's outward normal, only centres whose rest normal faces
        the same way (positive dot product) are taken, when one is among the 8 nearest: a push on
        one side of a part thinner than a patch is not put on the other side.

        Raises
        ------
        ValueError
            ``point`` (or ``normal``) is not 3 finite numbers.
        """
        q = np.asarray(point, dtype=np.float64)
        if q.shape != (3,) or not np.isfinite(q).all():
            raise ValueError(f"point must be 3 finite numbers [m], got {point!r}")
        nq: FloatArray | None = None
        if normal is not None:
            nq = np.asarray(normal, dtype=np.float64)
            if nq.shape != (3,) or not np.isfinite(nq).all():
                raise ValueError(f"normal must be 3 finite numbers, got {normal!r}")
        if previous is not None and 0 <= previous < len(self._rest):
            d = q - self._rest[previous]
            n = self._normals[previous]
            tangential = d - float(d @ n) * n
            near = float(tangential @ tangential) <= (HYSTERESIS * self._spacing) ** 2
            if near and (nq is None or float(n @ nq) > 0.0):
                return int(previous)
        if nq is None:
            _, i = self._tree.query(q)
            return int(self.centres[int(i)])
        k = min(8, len(self.centres))
        _, ids = self._tree.query(q, k=k)
        ids = np.atleast_1d(ids)
        centres = self.centres[ids]
        facing = self._normals[centres] @ nq > 0.0
        return int(centres[int(np.argmax(facing))] if facing.any() else centres[0])

    def around(self, key: int, radius_m: float) -> IntArray:
        """The centres within ``radius_m`` [m] of centre ``key``'s rest position that face its
        side (positive dot product of rest normals), nearest first, ``key`` excluded: where a
        contact at ``key`` may go next (:meth:`PatchCache.missing`, prefetching)."""
        here = self._rest[int(key)]
        ids = np.asarray(self._tree.query_ball_point(here, float(radius_m)), dtype=np.int64)
        centres = self.centres[ids]
        keep = (centres != int(key)) & (self._normals[centres] @ self._normals[int(key)] > 0.0)
        centres = centres[keep]
        return centres[np.argsort(np.linalg.norm(self._rest[centres] - here, axis=1))]


class PatchCache(Generic[_S]):
    """Least-recently-used cache of patch solves by patch key, solving misses in one batch.

    Both objects keep one solve per patch centre (a sparse solve is their dearest step); this
    is their cache. ``capacity`` entries are kept (more while one call needs them all).

    Parameters
    ----------
    capacity : int
        Entries kept (>= 1).
    solve : callable
        ``solve(keys)`` -> one entry per key, in order: the batch of missing patches.
    """

    def __init__(self, capacity: int, solve: Callable[[list[int]], list[_S]]) -> None:
        self._entries: OrderedDict[int, _S] = OrderedDict()
        self._capacity = int(capacity)
        self._solve = solve
        #: Number of patches solved so far (cache misses).
        self.solves = 0
        #: Number of patches stored by :meth:`put` (solved ahead, off the tick).
        self.prefetched = 0

    def peek(self, key: int) -> _S | None:
        """The cached entry of ``key``, or None (its recency unchanged)."""
        return self._entries.get(int(key))

    def clear(self) -> None:
        """Drop every entry."""
        self._entries.clear()

    def missing(self, keys: Sequence[int]) -> list[int]:
        """The keys among ``keys`` not cached (first occurrences, in order)."""
        return [k for k in dict.fromkeys(int(k) for k in keys) if k not in self._entries]

    def solve_detached(self, keys: Sequence[int]) -> list[_S]:
        """Solve ``keys`` without touching the cache (safe from a worker thread while the owner
        keeps ticking: the objects' solves only read their factor); :meth:`put` stores them."""
        return self._solve([int(k) for k in keys])

    def put(self, keys: Sequence[int], entries: Sequence[_S]) -> None:
        """Store entries solved by :meth:`solve_detached` (those already cached are kept)."""
        added = 0
        for k, entry in zip(keys, entries, strict=True):
            if int(k) not in self._entries:
                self._entries[int(k)] = entry
                added += 1
        self.prefetched += added
        while len(self._entries) > self._capacity:
            self._entries.popitem(last=False)

    def get(self, keys: Sequence[int]) -> list[_S]:
        """The entries of ``keys`` (in order, repeats allowed), solving the missing ones at once."""
        unique = list(dict.fromkeys(int(k) for k in keys))
        missing = [k for k in unique if k not in self._entries]
        if missing:
            for k, entry in zip(missing, self._solve(missing), strict=True):
                self._entries[k] = entry
            self.solves += len(missing)
        out = []
        for k in keys:
            self._entries.move_to_end(int(k))
            out.append(self._entries[int(k)])
        while len(self._entries) > max(self._capacity, len(unique)):
            self._entries.popitem(last=False)
        return out


#: Prefetch looks for uncached patch centres within this many patch spacings of a contact's.
AHEAD_SPACINGS = 1.6

#: Centres stood in for that wait to be solved ahead at most (the oldest are dropped: a hand
#: that asked for them has long moved on).
WANTED_MAX = 32


class PatchedSurface:
    """What both deformable objects share: a surface, its patch centres, the patch cache, and
    solving the patches a contact may move to next off the simulation tick (a base class).

    A subclass sets ``params`` (with ``sim_period_s``, ``patch_radius_m``, ``patch_spacing_m``),
    ``_rest`` (n, 3) [m], ``_normals`` (n, 3), ``_faces`` (m, 3) int32, ``_centres``
    (:class:`PatchCentres`) and ``_cache`` (:class:`PatchCache`). Prefetching:
    :meth:`patches_ahead` (which to solve), :meth:`solve_ahead` (the solve, safe from a worker
    thread: it only reads the factor) and :meth:`store_ahead` (into the cache, from the thread
    that ticks); a contact that slides onto a prefetched centre costs the tick no sparse solve
    (``server.prefetch``).
    """

    params: Any
    _rest: FloatArray
    _normals: FloatArray
    _faces: npt.NDArray[np.int32]
    _centres: PatchCentres
    _cache: PatchCache[Any]

    @property
    def n_vertices(self) -> int:
        """Number of surface vertices n."""
        return len(self._rest)

    @property
    def rest_vertices(self) -> FloatArray:
        """(n, 3) float64 [m] surface rest positions (read-only)."""
        return self._rest

    @property
    def rest_normals(self) -> FloatArray:
        """(n, 3) float64 outward unit surface normals at rest (read-only)."""
        return self._normals

    @property
    def faces(self) -> npt.NDArray[np.int32]:
        """(m, 3) int32 surface triangles, outward (counter-clockwise) winding."""
        return self._faces

    @property
    def sim_period_s(self) -> float:
        """Simulation period N*T [s] of one ``step``."""
        return float(self.params.sim_period_s)

    @property
    def patch_radius_m(self) -> float:
        """Finger-pad patch radius [m]."""
        return float(self.params.patch_radius_m)

    @property
    def solve_count(self) -> int:
        """Number of patch right-hand sides solved on demand so far (cache misses)."""
        return self._cache.solves

    def _pushes(self, keys: Sequence[int], forces_n: npt.ArrayLike) -> tuple[FloatArray, list[Any]]:
        """The checked push magnitudes (m,) [N] of a ``step`` and the cached solves of their
        patches (solving the missing ones).

        Raises
        ------
        ValueError
            Lengths differ or a force is not finite (nothing is solved).
        """
        f = np.asarray(forces_n, dtype=np.float64).reshape(-1)
        if len(f) != len(keys):
            raise ValueError(f"got {len(keys)} patch keys but {len(f)} forces")
        if not np.isfinite(f).all():
            raise ValueError("forces must be finite")
        return f, (self._cache.get(keys) if len(keys) else [])

    def patch_key(
        self,
        point: npt.ArrayLike,
        previous: int | None = None,
        normal: npt.ArrayLike | None = None,
        free: bool = False,
    ) -> int:
        """Cache key of the load patch for a contact at ``point`` (3,) [m]: the nearest centre.

        See :meth:`PatchCentres.key` (hysteresis with ``previous``, the side facing ``normal``).
        With patches solved ahead (:attr:`stand_in_m` > 0), a centre not solved yet is stood in
        for by a solved one within :attr:`stand_in_m`; for a probe in ``free`` space (not
        touching, nor within the world's proximity of the surface), where nothing is pushed and
        the patch only reports K_o and B_o ahead of a touch, by ``previous`` if solved, else by
        the nearest solved centre facing the same side at any distance: a hand moving through
        the air outruns the solves ahead, and each miss solved in the tick stalled every user's
        tick (40-60 ms on the palpation solid), which a client measures as a longer round trip
        (docs/fem.md, "A hand in the air"). Its own centre is solved ahead first.

        Raises
        ------
        ValueError
            ``point`` (or ``normal``) is not 3 finite numbers.
        """
        k = self._centres.key(point, previous, normal)
        if self.stand_in_m > 0.0 and self._cache.peek(k) is None:
            if free and previous is not None and self._cache.peek(int(previous)) is not None:
                return self._stand_in(k, int(previous))
            reach = math.inf if free else self.stand_in_m
            for c in self._centres.around(k, reach):
                if self._cache.peek(int(c)) is not None:
                    return self._stand_in(k, int(c))
        return k

    def _stand_in(self, wanted: int, solved: int) -> int:
        """``solved`` loads the contact whose centre ``wanted`` is solved ahead first."""
        self.stand_ins += 1
        if self._wanted is None:
            self._wanted = {}
        self._wanted.pop(wanted, None)
        self._wanted[wanted] = None  # the newest last
        while len(self._wanted) > WANTED_MAX:  # a hand long gone from the oldest
            del self._wanted[next(iter(self._wanted))]
        return solved

    #: With patches solved ahead (``server.prefetch``): a contact whose centre is not solved yet
    #: is loaded, for the ticks until it is, at the nearest solved centre within this distance
    #: [m] facing its side (a stand-in), so the tick never waits for a sparse solve; its own
    #: centre is solved ahead first. 0: off (the tick solves it).
    stand_in_m: float = 0.0
    #: Contacts loaded at a stand-in centre so far.
    stand_ins: int = 0
    #: Centres stood in for and not handed to :meth:`patches_ahead` yet, oldest first.
    _wanted: dict[int, None] | None = None

    def patches_ahead(self, keys: Sequence[int], limit: int) -> list[int]:
        """Up to ``limit`` uncached centres: those stood in for first (:attr:`stand_in_m`), the
        newest first, then around the patch centres ``keys``, each key's nearest first, the keys
        taken in turn (so every contact gets its next patch).

        A centre stood in for stays asked for until it is handed out here: a hand sweeping
        through the air asks a new centre every tick, more than one job solves, and the centre
        it is over now is the one it needs."""
        radius = AHEAD_SPACINGS * float(self.params.patch_spacing_m)
        rings = [self._centres.around(int(k), radius) for k in dict.fromkeys(keys)]
        out: list[int] = []
        seen: set[int] = set()
        if self._wanted:
            newest_first = list(reversed(self._wanted))
            for k in self._cache.missing(newest_first):
                seen.add(k)
                out.append(k)
                if len(out) >= limit:
                    break
            # the handed-out and the solved leave the queue; the rest wait for the next job
            for k in newest_first:
                if k in seen or self._cache.peek(k) is not None:
                    del self._wanted[k]
        if len(out) >= limit:
            return out
        for depth in range(max((len(r) for r in rings), default=0)):
            wanted = [int(r[depth]) for r in rings if depth < len(r)]
            for k in self._cache.missing(wanted):
                if k not in seen:
                    seen.add(k)
                    out.append(k)
                    if len(out) >= limit:
                        return out
        return out

    def solve_ahead(self, keys: Sequence[int]) -> list[Any]:
        """The solves of ``keys``, the cache untouched (:meth:`PatchCache.solve_detached`)."""
        return self._cache.solve_detached(keys)

    def store_ahead(self, keys: Sequence[int], solves: Sequence[Any]) -> None:
        """Cache solves made by :meth:`solve_ahead` (:meth:`PatchCache.put`)."""
        self._cache.put(keys, solves)

    @property
    def prefetch_count(self) -> int:
        """Patches solved ahead and stored so far."""
        return self._cache.prefetched
