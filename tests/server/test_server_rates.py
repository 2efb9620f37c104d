"""The server's rates are declared once: the object, the world and the room agree on N*T."""

from __future__ import annotations

import json

import pytest

from haptic_collab.server.main import ServerOptions, build_rates, build_world
from haptic_collab.server.objects.balloon import Balloon, BalloonParams
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.room import Room
from haptic_collab.server.world import World
from haptic_collab.shared.protocol import PROTOCOL_VERSION
from haptic_collab.shared.rates import Rates


@pytest.fixture(scope="module")
def balloon_20hz() -> Balloon:
    return Balloon(default_balloon(0.1, 2), BalloonParams(sim_period_s=1.0 / 20.0))


def _welcome(room: Room) -> dict:
    room.connect("c", 0.0)
    hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "name": "A", "role": "user"}
    (out,) = [o for o in room.receive("c", json.dumps(hello), 0.0) if isinstance(o.data, str)]
    welcome = json.loads(out.data)
    assert welcome["type"] == "welcome", welcome
    return welcome


def test_the_server_builds_object_world_and_room_from_one_rates():
    rates = build_rates(ServerOptions(sim_rate_hz=25.0, subdivisions=1))
    assert (rates.servo_rate_hz, rates.sim_rate_hz, rates.ratio) == (1000.0, 25.0, 40)
    world = build_world(ServerOptions(sim_rate_hz=25.0, subdivisions=1), rates)
    assert world.rates is rates and world.sim_period_s == rates.sim_period_s == 0.04
    room = Room(world)  # the world's rates
    assert room.rates is rates and room.sim_rate_hz == 25.0
    assert _welcome(room)["sim_rate_hz"] == 25.0


def test_a_room_at_another_rate_than_its_balloon_is_refused(balloon_20hz):
    world = World(balloon_20hz)
    with pytest.raises(ValueError, match=r"steps every 50 ms \(20 Hz\).*25 Hz"):
        Room(world, Rates(1000.0, 25.0))
    with pytest.raises(ValueError, match=r"steps every 50 ms \(20 Hz\).*given 30 Hz"):
        Room(world, 30.0)  # a bare rate (older callers) is checked as well
    with pytest.raises(ValueError, match="needs its rates"):
        Room(world)  # neither the room nor the world knows the rates
    # the same declaration, as Rates or as a bare rate, is accepted
    assert Room(world, Rates(1000.0, 20.0)).sim_rate_hz == 20.0
    assert _welcome(Room(world, 20.0))["sim_rate_hz"] == 20.0


def test_a_world_at_another_rate_than_its_balloon_is_refused(balloon_20hz):
    with pytest.raises(ValueError, match=r"the object steps every 50 ms \(20 Hz\).*40 ms"):
        World(balloon_20hz, rates=Rates(1000.0, 25.0))
    assert World(balloon_20hz, rates=Rates(500.0, 20.0)).rates == Rates(500.0, 20.0)


def test_build_world_refuses_rates_that_disagree_with_the_options():
    with pytest.raises(ValueError, match="25 Hz disagree with --sim-rate 20 Hz"):
        build_world(ServerOptions(sim_rate_hz=20.0, subdivisions=1), Rates(1000.0, 25.0))


def test_a_sim_rate_the_servo_rate_is_no_multiple_of_is_refused_with_the_usual_message():
    with pytest.raises(ValueError, match=r"--sim-rate 30 Hz: .*N = 33\.3.*10, 20, 25, 40"):
        build_rates(ServerOptions(sim_rate_hz=30.0))
    with pytest.raises(ValueError, match=r"--sim-rate must be in \[1, 1000\] Hz"):
        build_rates(ServerOptions(sim_rate_hz=2000.0))
