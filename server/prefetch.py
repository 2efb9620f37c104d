"""Solve the load patches a contact may move to next in a worker thread, between ticks.

A contact that slides onto a patch centre whose solve is not cached costs the simulation tick a
sparse solve: about 1 ms on the 2562-vertex balloon, 50 ms per patch on a FEM solid of 10k
surface vertices (``haptic bench server``), which is what the tick's p99 was made of. The
:class:`PatchPrefetcher` solves, after each tick, the uncached centres next to every user's
current one (:meth:`server.world.World.patches_ahead`) in one worker thread (SciPy's SuperLU
releases the GIL while it solves; the solves only read the factor) and stores them in the
object's cache on the next call from the ticking thread, so the tick finds them there.

This is the server's I/O side: :mod:`server.world` and the objects stay free of threads.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

from haptic_collab.server.objects.patches import AHEAD_SPACINGS

log = logging.getLogger("haptic.server")

#: Patches solved per job: small, so a job is done within a tick or two.
PREFETCH_BATCH = 4


class PatchPrefetcher:
    """One worker thread solving the patches ahead of the users' contacts.

    Call :meth:`after_tick` from the thread that ticks the world, after each tick: it stores a
    finished job's solves in the object's cache and starts the next job. Not thread-safe itself;
    :meth:`close` stops the worker.

    Parameters
    ----------
    world : server.world.World
        The world whose object is prefetched (an object without
        :class:`server.objects.patches.PatchedSurface` makes this a no-op).
    batch : int
        Patches per job (>= 1).
    stand_in : bool
        A contact whose centre is not solved yet is loaded at a solved centre within the
        prefetch ring (``AHEAD_SPACINGS`` patch spacings) until it is
        (:attr:`server.objects.patches.PatchedSurface.stand_in_m`); False: the tick solves it.
    """

    def __init__(self, world: Any, batch: int = PREFETCH_BATCH, stand_in: bool = True) -> None:
        if int(batch) < 1:
            raise ValueError(f"batch must be >= 1, got {batch}")
        self.world = world
        self.batch = int(batch)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="patch-prefetch")
        # a contact whose centre is not solved yet borrows a solved neighbour's meanwhile
        # (PatchedSurface.stand_in_m), so the tick never waits for a sparse solve
        obj = getattr(world, "obj", None)
        if obj is not None and hasattr(obj, "stand_in_m"):
            spacing = float(obj.params.patch_spacing_m)
            obj.stand_in_m = AHEAD_SPACINGS * spacing if stand_in else 0.0

        self._job: tuple[list[int], Future[list[Any]]] | None = None
        #: Jobs whose solve raised (logged; the tick then solves those patches itself).
        self.failures = 0

    def after_tick(self) -> None:
        """Store the finished job's solves, then start the next job if there is one."""
        if self._job is not None:
            keys, future = self._job
            if not future.done():
                return
            self._job = None
            try:
                solves = future.result()
            except Exception:  # the tick will solve these itself; the server keeps running
                self.failures += 1
                log.exception("prefetching patches %s failed", keys)
            else:
                self.world.obj.store_ahead(keys, solves)
        ahead = getattr(self.world, "patches_ahead", None)
        keys = ahead(self.batch) if ahead is not None else []
        if keys:
            self._job = (keys, self._pool.submit(self.world.obj.solve_ahead, keys))

    def close(self) -> None:
        """Stop the worker (a running job is finished and dropped); the object's contacts get
        their own centres again."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._job = None
        obj = getattr(self.world, "obj", None)
        if obj is not None and hasattr(obj, "stand_in_m"):
            obj.stand_in_m = 0.0
