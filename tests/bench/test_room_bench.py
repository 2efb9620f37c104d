"""``haptic bench server``'s room tick (:func:`haptic_collab.bench.world.bench_room`): the
server's whole simulation tick with the load bench's scripted users and viewers, no sockets."""

from __future__ import annotations

import pytest

from haptic_collab.bench.world import bench_room


def test_room_bench_ticks_the_load_benchs_users_with_their_gains_found():
    r = bench_room(users=4, viewers=1, subdivisions=3, ticks=12, warmup=20)
    assert r["benchmark"] == "room_tick"
    assert (r["users"], r["viewers"], r["n_vertices"], r["ticks"]) == (4, 1, 642, 12)
    # every timed patch of every user carried gains: the designs were made in the warm-up
    assert r["gain_hits"] == 4 * 12 and r["gain_misses"] == 0
    # the world's tick and the gain advice are parts of the room's tick
    assert 0.0 < r["world_cpu_ms_p50"] <= r["tick_cpu_ms_p50"] <= r["tick_cpu_ms_p99"]
    assert 0.0 < r["gains_cpu_ms_p50"] <= r["tick_cpu_ms_p50"]


@pytest.mark.parametrize("users", [0, 33])
def test_room_bench_refuses_more_users_than_the_load_bench_places(users):
    with pytest.raises(ValueError, match="users"):
        bench_room(users=users)
