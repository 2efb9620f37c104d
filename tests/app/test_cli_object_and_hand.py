"""``--stiffness-scale`` and ``--hand-*``: a stiffer object and another simulated hand, end to end."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from haptic_collab.cli import build_parser, main
from haptic_collab.cli.run import _client_options, _server_options
from haptic_collab.client.devices.opener import make_device
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.demo import DemoOptions
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.objects.balloon import BalloonParams
from haptic_collab.server.world import ContactInput, World

TOP = (0.0, 0.0, 0.1)
UP = (0.0, 0.0, 1.0)


def k_o_at_top(world: World) -> float:
    """K_o [N/m] the server reports to a user whose probe is just above the top."""
    probe = np.array([0.0, 0.0, world.rest_bounds[1, 2] + 0.005])
    return world.tick({"u": ContactInput(probe=probe, force=np.zeros(3))})["u"].k_o


def test_stiffness_scale_multiplies_k_o() -> None:
    parse = build_parser().parse_args
    plain = build_world(_server_options(parse(["server"])))
    stiff = build_world(_server_options(parse(["server", "--stiffness-scale", "3.3"])))
    assert k_o_at_top(stiff) == pytest.approx(3.3 * k_o_at_top(plain), rel=0.01)
    assert k_o_at_top(stiff) > 900.0  # about the paper's 1 N/mm of Fig. 10-11


def test_stiffness_scale_scales_every_stiffness_term_and_not_damping() -> None:
    p = dataclasses.replace(BalloonParams(), damping=2.0)
    s = p.with_stiffness_scale(2.5)
    for name in ("tension", "bending", "foundation", "bulk"):
        assert getattr(s, name) == pytest.approx(2.5 * getattr(p, name))
    assert s.damping == p.damping and s.patch_radius_m == p.patch_radius_m
    with pytest.raises(ValueError):
        build_world(ServerOptions(stiffness_scale=float("nan")))


def device_for(argv: list[str]) -> SimDevice:
    """The device ``haptic client ARGV`` builds (the call client.app makes)."""
    opts = _client_options(build_parser().parse_args(["client", *argv]))
    dev = make_device(
        opts.device,
        TOP,
        UP,
        profile=opts.profile,
        trajectory_options=opts.trajectory or None,
        servo_rate_hz=opts.servo_rate_hz,
    )
    assert isinstance(dev, SimDevice)
    return dev


def test_hand_flags_reach_the_simulated_hand() -> None:
    dev = device_for(
        ["--hand-mass", "0.3", "--hand-stiffness", "150", "--hand-damping", "2.5",
         "--trajectory", "depth_m=0.012"]
    )  # fmt: skip
    assert dev.hand == HandParams(stiffness_n_per_m=150.0, damping_n_s_per_m=2.5, mass_kg=0.3)
    assert dev.trajectory.depth_m == 0.012  # type: ignore[attr-defined]
    assert device_for([]).hand == HandParams()
    only = device_for(["--device", "sim:rest", "--hand-stiffness", "450"]).hand
    assert only == dataclasses.replace(HandParams(), stiffness_n_per_m=450.0)


def test_demo_passes_the_hand_to_both_clients() -> None:
    opts = DemoOptions(hand_mass_kg=0.2, hand_damping_n_s_per_m=8.0, stiffness_scale=3.3)
    args = build_parser().parse_args(["client", *opts.hand_args()])
    assert (args.hand_mass, args.hand_stiffness, args.hand_damping) == (0.2, None, 8.0)
    assert DemoOptions().hand_args() == []
    demo = build_parser().parse_args(["demo", "--stiffness-scale", "3.3", "--hand-mass", "0.2"])
    assert demo.stiffness_scale == 3.3 and demo.hand_mass == 0.2


@pytest.mark.parametrize(
    "argv",
    [
        ["server", "--stiffness-scale", "0"],
        ["server", "--stiffness-scale", "-2"],
        ["server", "--stiffness-scale", "nan"],
        ["demo", "--stiffness-scale", "0"],
        ["client", "--hand-mass", "-1"],
        ["client", "--hand-stiffness", "0"],
        ["client", "--hand-damping", "nan"],
        ["demo", "--hand-stiffness", "-300"],
    ],
)
def test_bad_values_exit_2_with_one_line(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and captured.out == ""


def test_no_rest_plane_reaches_the_client_options() -> None:
    # alone in the room the client renders the rest plane the server sends; --no-rest-plane
    # keeps the design through the simulation (client.app passes it to ClientSession)
    parse = build_parser().parse_args
    assert _client_options(parse(["client"])).rest_plane is True
    assert _client_options(parse(["client", "--no-rest-plane"])).rest_plane is False
