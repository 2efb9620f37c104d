"""Patches solved ahead, between ticks: a contact that slides costs the tick no sparse solve."""

from __future__ import annotations

import time

import numpy as np
import pytest

from haptic_collab.server.objects.balloon import Balloon
from haptic_collab.server.prefetch import PatchPrefetcher
from haptic_collab.server.world import ContactInput, World

R = 0.1


def _drain(prefetcher: PatchPrefetcher, world: World, timeout_s: float = 20.0) -> None:
    """Call after_tick until nothing is left to solve around the users."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        prefetcher.after_tick()
        if prefetcher._job is None and not world.patches_ahead(prefetcher.batch):
            return
        time.sleep(0.005)
    raise AssertionError("prefetching did not finish")


def _slide(world: World, ticks: int, step_m: float) -> int:
    """A probe 3 mm into the balloon sliding from the top along +x; the solves on the ticks."""
    before = world.obj.solve_count
    for k in range(ticks):
        phi = k * step_m / R
        probe = (R - 0.003) * np.array([np.sin(phi), 0.0, np.cos(phi)])
        world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
    return int(world.obj.solve_count - before)


def test_a_sliding_contact_finds_its_next_patches_solved():
    """Without prefetching, every new patch centre the contact slides onto is a sparse solve on
    the tick; with the patches around the contact solved between ticks, none is."""
    plain = World(Balloon())
    on_tick_plain = _slide(plain, 40, 0.0005)
    assert on_tick_plain >= 2  # the slide crosses several patch centres

    world = World(Balloon())
    prefetcher = PatchPrefetcher(world)
    try:
        _slide(world, 1, 0.0)
        _drain(prefetcher, world)
        on_tick = 0
        for k in range(1, 40):
            phi = k * 0.0005 / R
            probe = (R - 0.003) * np.array([np.sin(phi), 0.0, np.cos(phi)])
            before = world.obj.solve_count
            world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
            on_tick += world.obj.solve_count - before
            _drain(prefetcher, world)
        assert on_tick == 0
        assert world.obj.prefetch_count >= on_tick_plain
    finally:
        prefetcher.close()


def test_prefetched_patches_are_the_same_solves():
    """A patch solved ahead in the worker gives the compliance a solve on the tick gives."""
    a, b = Balloon(), Balloon()
    key = a.patch_key(np.array([0.0, 0.0, R]))
    ahead = a.patches_ahead([key], 3)
    assert len(ahead) == 3 and key not in ahead
    a.store_ahead(ahead, a.solve_ahead(ahead))
    assert a.solve_count == 0 and a.prefetch_count == 3
    np.testing.assert_allclose(
        a.contact_compliance(ahead), b.contact_compliance(ahead), rtol=1e-12, atol=0.0
    )
    assert a.solve_count == 0
    assert a.patches_ahead([key], 3)[:1] != ahead[:1]  # the solved ones are not offered again


def test_a_failing_prefetch_is_logged_and_the_tick_still_solves(caplog):
    world = World(Balloon())
    world.tick({"u": ContactInput(probe=np.array([0.0, 0.0, R - 0.003]), force=np.zeros(3))})

    def broken(keys):
        raise RuntimeError("worker lost")

    world.obj.solve_ahead = broken  # type: ignore[method-assign]
    prefetcher = PatchPrefetcher(world)
    try:
        prefetcher.after_tick()
        time.sleep(0.05)
        prefetcher.after_tick()
        assert prefetcher.failures == 1
        assert "prefetching patches" in caplog.text
    finally:
        prefetcher.close()
    out = world.tick({"u": ContactInput(probe=np.array([0.003, 0, R - 0.003]), force=np.zeros(3))})
    assert out["u"].k_o > 0.0


def test_bad_batch_is_refused():
    with pytest.raises(ValueError, match="batch"):
        PatchPrefetcher(World(Balloon()), batch=0)


def test_a_fast_contact_borrows_a_solved_neighbour_and_its_own_centre_is_solved_next():
    """A contact that jumps to a centre not solved yet is loaded at the nearest solved centre
    on its side for that tick (no sparse solve on the tick), and its own centre is the first one
    solved ahead; the next tick it has its own."""
    world = World(Balloon())
    prefetcher = PatchPrefetcher(world)
    obj = world.obj
    try:
        assert obj.stand_in_m > 0.0
        _slide(world, 1, 0.0)
        _drain(prefetcher, world)
        # a jump of 1.3 patch spacings along the surface, past the ring already solved
        step = 1.3 * obj.params.patch_spacing_m
        phi = step / R
        probe = (R - 0.003) * np.array([np.sin(phi), 0.0, np.cos(phi)])
        own = obj.patch_key(probe, None, probe / np.linalg.norm(probe))
        obj._cache._entries.pop(own, None)  # its own centre not solved yet
        before, stood = obj.solve_count, obj.stand_ins
        world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
        assert obj.solve_count == before  # the tick did not solve
        assert obj.stand_ins == stood + 1
        assert world.patches_ahead(1) == [own]  # its own centre is solved first
        _drain(prefetcher, world)
        world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
        assert obj.solve_count == before
        assert world._users["u"].key == own
    finally:
        prefetcher.close()
    assert obj.stand_in_m == 0.0  # closed: contacts get their own centres again


def test_a_hand_moving_in_the_air_costs_the_tick_no_solve_and_touches_its_own_patch():
    """A probe 2 cm above the surface sweeping a quarter of the way round it (faster than the
    ring solved ahead) keeps solved patches meanwhile, so no tick waits for a sparse solve (each
    one 40-60 ms on the palpation solid); a probe in contact still gets its own centre's solve."""
    world = World(Balloon())
    prefetcher = PatchPrefetcher(world)
    obj = world.obj
    try:
        _slide(world, 1, 0.0)
        _drain(prefetcher, world)
        before = obj.solve_count
        for k in range(1, 30):
            phi = k * (np.pi / 2) / 30
            probe = (R + 0.02) * np.array([np.sin(phi), 0.0, np.cos(phi)])
            out = world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
            assert not out["u"].in_contact and out["u"].k_o > 0.0
            prefetcher.after_tick()
        assert obj.solve_count == before  # not one sparse solve on a tick
        # once its own centre is solved ahead, the hand has its own patch
        assert obj.stand_ins > 0  # it went on solved stand-ins meanwhile
        _drain(prefetcher, world)
        stood = obj.stand_ins
        world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
        assert obj.stand_ins == stood and obj.solve_count == before  # its own, solved ahead
        # the hand comes down: in contact at the side, where the ring around it is not solved
        _drain(prefetcher, world)
        probe = (R - 0.003) * np.array([1.0, 0.0, 0.0])
        obj._cache._entries.clear()
        world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
        own = obj.patch_key(probe, None, probe / np.linalg.norm(probe))
        assert world._users["u"].key == own  # nothing solved near it: the tick solved its own
        assert obj.solve_count > before
    finally:
        prefetcher.close()


def test_a_hand_sweeping_past_a_busy_worker_gets_the_centre_it_is_over_solved_first():
    """The worker is still busy with one job while the hand sweeps over many centres (a slow
    solve on a busy machine); once it is free, the centre the hand is over now is solved first,
    and the hand has its own patch without a tick solving it (CI saw it lost: the queue of
    centres stood in for was cut to one job's worth, the oldest kept)."""
    import threading

    world = World(Balloon())
    prefetcher = PatchPrefetcher(world)
    obj = world.obj
    release = threading.Event()
    solve = obj.solve_ahead

    def held(keys):
        release.wait(10.0)
        return solve(keys)

    try:
        _slide(world, 1, 0.0)
        _drain(prefetcher, world)
        obj.solve_ahead = held  # type: ignore[method-assign]
        before = obj.solve_count
        for k in range(1, 30):
            phi = k * (np.pi / 2) / 30
            probe = (R + 0.02) * np.array([np.sin(phi), 0.0, np.cos(phi)])
            world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
            prefetcher.after_tick()
        own = obj.patch_key(probe, world._users["u"].key, probe / np.linalg.norm(probe))
        assert world._users["u"].key != own  # stood in for: its own is not solved yet
        assert prefetcher._job is not None
        held_job = prefetcher._job
        release.set()
        held_job[1].result(timeout=10.0)
        prefetcher.after_tick()  # stores the held job, starts the next
        assert prefetcher._job is not None and prefetcher._job[0][0] == own
        _drain(prefetcher, world)
        world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})
        assert world._users["u"].key == own
        assert obj.solve_count == before  # no tick solved
    finally:
        release.set()
        prefetcher.close()
