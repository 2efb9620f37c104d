"""The local model update from the server's contact to the servo's force, through the wire.

The room encodes a real world's surface patch as a ``patch``; the client reads the same
:class:`SurfacePatch` back, wraps it in a :class:`LocalModelUpdate` and the servo renders it: the force the user feels must be the one of
the server's own primitive, K_h times the probe's depth along its normal, for a plane and for a
sphere, and the same as the servo rendered when handed the primitive and gains one by one.
"""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.server.objects.balloon import Balloon, BalloonParams
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.room import Room
from haptic_collab.server.world import World
from haptic_collab.shared.local_model_update import (
    LocalModelUpdate,
    SurfacePatch,
    primitive_from_wire,
    primitive_to_wire,
)
from haptic_collab.shared.primitives import Plane, Sphere, make_plane, make_sphere
from haptic_collab.shared.protocol import (
    PROTOCOL_VERSION,
    Patch,
    PlaneModel,
    ProtocolError,
    SphereModel,
    parse_server,
)
from tests.support.helpers import FakeDevice

SIM_RATE_HZ = 20.0
K_H = 300.0
#: Where the user's probe is: 3 mm into the top of the 0.1 m balloon, off its axis.
PROBE = (0.012, -0.007, 0.097)


class RecordingWorld:
    """A real world that keeps the contacts it returned (what the room put on the wire)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.outputs: dict[str, SurfacePatch] = {}

    def tick(self, inputs: Any, tick: int | None = None) -> dict[str, SurfacePatch]:
        self.outputs = self.world.tick(inputs, tick)
        return self.outputs

    def __getattr__(self, name: str) -> Any:
        return getattr(self.world, name)


def server_patch(primitive: str) -> tuple[SurfacePatch, Patch]:
    """One user's contact after a tick of a real balloon, and the patch the room sent for it."""
    world = RecordingWorld(
        World(
            Balloon(default_balloon(0.1, 3), BalloonParams(sim_period_s=1.0 / SIM_RATE_HZ)),
            primitive=primitive,  # type: ignore[arg-type]
        )
    )
    room = Room(world, SIM_RATE_HZ)  # type: ignore[arg-type]
    room.connect("a", 0.0)
    hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "role": "user", "name": "A"}
    room.receive("a", json.dumps(hello), 0.0)
    state = {"type": "state", "seq": 1, "probe_m": list(PROBE), "force_n": [0.0, 0.0, 0.0]}
    room.receive("a", json.dumps(state), 0.0)
    out = room.tick(1, 0.0)
    (frame,) = [o.data for o in out if o.conn_id == "a" and o.stream == "patch"]
    assert isinstance(frame, str)
    msg = parse_server(frame)
    assert isinstance(msg, Patch)
    return world.outputs["a"], msg


def rendered_force(set_patch: Any) -> np.ndarray:
    """The force [N] the servo displays with the probe held at PROBE, once forces are up."""
    dev = FakeDevice(PROBE)
    core = ServoCore(dev, ServoConfig(ramp_s=0.02))
    core.enable_forces()
    set_patch(core)
    for k in range(60):  # the safety gain ramps up over 20 ticks
        core.notify_link(k * 1e-3)
        core.tick(k * 1e-3)
    return np.array(dev.displayed)


@pytest.mark.parametrize("primitive", ["plane", "sphere"])
def test_the_servo_renders_the_servers_contact_through_the_wire(primitive: str) -> None:
    res, msg = server_patch(primitive)
    assert isinstance(res.primitive, Sphere if primitive == "sphere" else Plane)
    surface = SurfacePatch.from_wire(msg)
    assert surface == res  # one type: the world's surface patch is what the client reads back
    update = LocalModelUpdate.from_surface(surface, k_h=K_H, i_gain=0.0, hold_ticks=50)

    assert type(update.primitive) is type(res.primitive)
    assert update.surface is not None
    assert (update.surface.tick, update.surface.k_o, update.surface.k_o_eff) == (
        1,
        res.k_o,
        res.k_o_eff,
    )
    assert (update.surface.b_o, update.surface.k_o_stiff) == (res.b_o, res.k_o_stiff)
    assert update.recovery_m_per_n == pytest.approx(1.0 / res.k_o)

    # the server's own primitive: K_h times the probe's depth, along the outward normal
    e, nx, ny, nz = res.primitive.contact(*PROBE)
    assert e > 0.001  # in contact: a force to compare
    expected = K_H * e * np.array([nx, ny, nz])

    new = rendered_force(lambda core: core.set_patch(update))
    assert new == pytest.approx(expected, rel=1e-9, abs=1e-12)

    # as before: the primitive rebuilt from the wire and handed over with the gains one by one
    p = msg.primitive
    prim = (
        make_plane(p.point, p.normal)
        if isinstance(p, PlaneModel)
        else make_sphere(p.center, p.radius)
    )
    old = rendered_force(lambda core: core.set_patch(prim, K_H, 0.0, hold_ticks=50, k_o=msg.k_o))
    assert new.tolist() == old.tolist()


def test_the_primitive_survives_the_wire_both_ways() -> None:
    plane = make_plane((0.0, 0.01, 0.1), (0.0, 0.0, 1.0))
    sphere = make_sphere((0.0, 0.0, 0.0), 0.1)
    assert primitive_to_wire(plane) == PlaneModel(point=(0.0, 0.01, 0.1), normal=(0.0, 0.0, 1.0))
    assert primitive_to_wire(sphere) == SphereModel(center=(0.0, 0.0, 0.0), radius=0.1)
    assert primitive_from_wire(primitive_to_wire(plane)) == plane
    assert primitive_from_wire(primitive_to_wire(sphere)) == sphere
    with pytest.raises(ProtocolError) as exc:
        primitive_from_wire(PlaneModel(point=(0, 0, 0), normal=(0, 0, 0)))
    assert exc.value.code == "invalid_primitive"


def test_an_uncoupled_patch_reads_back_k_o_as_its_stiffest_stiffness() -> None:
    msg = Patch(
        tick=3, primitive=PlaneModel(point=(0, 0, 0.1), normal=(0, 0, 1)), proxy_m=(0, 0, 0.1),
        normal=(0, 0, 1), penetration_m=0.001, in_contact=True, k_o=400.0, k_o_eff=380.0, b_o=2.0,
    )  # fmt: skip
    update = LocalModelUpdate.from_surface(
        SurfacePatch.from_wire(msg), k_h=200.0, i_gain=1000.0, b_h=1.0, proxy_hold="foh"
    )
    assert update.surface is not None and update.surface.k_o_stiff == 400.0
    assert (update.k_h, update.i_gain, update.b_h, update.proxy_hold) == (200.0, 1000.0, 1.0, "foh")


def test_an_update_set_by_hand_knows_no_object_stiffness() -> None:
    update = LocalModelUpdate(make_plane((0, 0, 0), (0, 0, 1)), 300.0, 0.0)
    assert update.surface is None and update.recovery_m_per_n is None


@pytest.mark.parametrize(
    "bad",
    [
        {"k_h": 0.0},
        {"i_gain": -1.0},
        {"b_h": float("nan")},
        {"proxy_hold": "soh"},
        {"hold_ticks": 0},
    ],
)
def test_bad_values_are_refused_when_the_update_is_built(bad: dict[str, Any]) -> None:
    args: dict[str, Any] = {"k_h": 300.0, "i_gain": 0.0, **bad}
    with pytest.raises(ValueError, match=next(iter(bad))):
        LocalModelUpdate(make_plane((0, 0, 0), (0, 0, 1)), **args)


@pytest.mark.parametrize(
    "bad",
    [
        {"k_o": 0.0},
        {"k_o_eff": float("inf")},
        {"k_o_stiff": float("nan")},
        {"b_o": -1.0},
        {"own_force_n": -0.5},
    ],
)
def test_bad_values_are_refused_when_the_surface_patch_is_built(bad: dict[str, Any]) -> None:
    good = SurfacePatch.of(make_plane((0, 0, 0), (0, 0, 1)), 400.0)
    with pytest.raises(ValueError, match=next(iter(bad))):
        replace(good, **bad)


def test_the_servo_takes_an_update_or_a_primitive_with_gains_but_not_both() -> None:
    core = ServoCore(FakeDevice(), ServoConfig())
    plane = make_plane((0, 0, 0), (0, 0, 1))
    update = LocalModelUpdate(plane, 5000.0, 0.0, surface=SurfacePatch.of(plane, 400.0))
    applied = core.set_patch(update)
    assert applied.k_h == 1000.0 and applied.surface == update.surface  # clamped to the device
    with pytest.raises(TypeError):
        core.set_patch(update, 300.0, 0.0)
    with pytest.raises(TypeError):
        core.set_patch(make_plane((0, 0, 0), (0, 0, 1)))
