"""N = servo rate / simulation rate must be a whole number (the local model's lifted loop, paper
section 3): rates that give a fractional N are refused with one clear line, on both sides."""

from __future__ import annotations

import asyncio

import pytest

from haptic_collab.cli import main
from haptic_collab.client.app import ClientOptions, run_client
from haptic_collab.server.app import ServerApp
from haptic_collab.server.objects.balloon import Balloon, BalloonParams
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.room import Room
from haptic_collab.server.world import World
from haptic_collab.shared.stability import dividing_rates


def test_the_server_refuses_a_rate_the_servo_loop_is_no_multiple_of(capsys):
    assert main(["server", "--sim-rate", "30", "--port", "0", "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert "--sim-rate 30 Hz" in err and "N = 33.3" in err and "25, 40" in err
    assert err.count("\n") == 1  # one line, no traceback


def test_rates_that_divide_the_servo_rate():
    assert dividing_rates(1000.0, 10.0, 250.0) == [10, 20, 25, 40, 50, 100, 125, 200, 250]
    assert dividing_rates(1024.0, 100.0, 600.0) == [128, 256, 512]


async def test_a_client_whose_servo_rate_does_not_fit_the_server_stops_at_once():
    # an older (or differently configured) server simulating at 30 Hz: built directly
    world = World(Balloon(default_balloon(subdivisions=2), BalloonParams(sim_period_s=1.0 / 30.0)))
    app = ServerApp(Room(world, 30.0), "127.0.0.1", 0)
    await app.start()
    try:
        opts = ClientOptions(
            url=f"ws://127.0.0.1:{app.port}/ws", device="sim:rest", duration_s=30.0
        )
        with pytest.raises(ValueError, match=r"--servo-rate 990\b"):
            await asyncio.wait_for(run_client(opts), 20.0)  # not the whole 30 s
    finally:
        await app.stop()
