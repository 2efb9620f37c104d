"""The simulation core: users push, the object deforms, everyone feels the current surface."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from haptic_collab.bench.world import bench_world
from haptic_collab.server.objects.balloon import Balloon
from haptic_collab.server.world import ContactInput, World
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.primitives import Plane, Sphere

R = 0.1
NO_FORCE = np.zeros(3)


@pytest.fixture
def world() -> World:
    return World(Balloon())


class PUser:
    """A user with a proportional local model along the normal (paper eq. 7-8), in 1-D."""

    def __init__(self, probe: list[float], k_h: float | None = None, fraction: float = 0.5) -> None:
        self.probe = np.asarray(probe, float)
        self.k_h = k_h
        self.fraction = fraction
        self.force = np.zeros(3)
        self.magnitude = 0.0

    def input(self) -> ContactInput:
        return ContactInput(probe=self.probe, force=self.force)

    def update(self, out: SurfacePatch) -> None:
        if self.k_h is None:
            self.k_h = self.fraction * out.k_o_eff
        self.magnitude = self.k_h * max(out.penetration_m, 0.0)
        self.force = self.magnitude * np.asarray(out.normal)


def run(world: World, users: dict[str, PUser], ticks: int) -> dict[str, SurfacePatch]:
    out: dict[str, SurfacePatch] = {}
    for _ in range(ticks):
        out = world.tick({name: u.input() for name, u in users.items()})
        for name, u in users.items():
            u.update(out[name])
    return out


def test_a_resting_user_feels_another_user_press_the_top(world):
    b = PUser([R - 0.0015, 0.0, 0.0])  # resting lightly on the equator, 1.5 mm in
    alone = run(world, {"B": b}, 30)
    force_alone, proxy_alone = b.magnitude, np.array(alone["B"].proxy)
    assert alone["B"].in_contact and force_alone > 0.05

    a = PUser([0.0, 0.0, R - 0.010], fraction=0.9)  # pressing 10 mm into the top
    users = {"A": a, "B": b}
    both = run(world, users, 150)
    ratio = b.magnitude / force_alone
    assert ratio >= 1.2, ratio  # B is pushed back by the water: >= 20 % more force
    assert both["B"].proxy[0] > proxy_alone[0] + 2e-4  # the side bulged out by a fraction of a mm
    assert a.magnitude > 1.0  # A feels a firm push
    assert both["A"].proxy[2] < R - 0.002  # and the top is dented
    # settled: one more tick changes nothing noticeable
    previous = b.magnitude
    run(world, users, 1)
    assert b.magnitude == pytest.approx(previous, rel=1e-4)
    # coupling is reported: both contacts get K_o_eff below K_o and a stiff mode above it
    for out in both.values():
        assert out.k_o_eff < out.k_o < out.k_o_stiff


@pytest.mark.parametrize("gain, stable", [(0.8, True), (1.2, False)])
def test_single_user_is_stable_iff_k_h_below_k_o(world, gain, stable):
    """Paper eq. (8) and Fig. 7(c): K_h > K_o makes the slow loop oscillate without end.

    (The contact is unilateral, so the divergence of the linear loop saturates into a limit
    cycle: the surface is thrown in, the probe loses contact, the surface comes back.)
    """
    first = world.tick({"A": ContactInput(np.array([0.0, 0.0, R - 0.005]), NO_FORCE)})["A"]
    user = PUser([0.0, 0.0, R - 0.005], k_h=gain * first.k_o_eff)
    depths = []
    for _ in range(60):
        out = run(world, {"A": user}, 1)["A"]
        depths.append(R - out.proxy[2])
    swing = abs(depths[-1] - depths[-2])
    if stable:
        assert swing < 1e-6
        assert 0.0 < depths[-1] < 0.005
    else:
        assert swing > 1e-3  # still jumping by millimetres every tick after 3 s


def test_nan_input_skips_the_load_but_still_answers_and_keeps_the_state(world):
    good = {"A": ContactInput(np.array([0.0, 0.0, R - 0.004]), np.array([0.0, 0.0, 1.0]))}
    reference = World(Balloon())
    reference.tick(good)
    out = world.tick(good)
    assert np.array_equal(world.vertices, reference.vertices)

    bad = dict(good)
    bad["N"] = ContactInput(np.array([np.nan, 0.0, 0.1]), np.array([0.0, 0.0, 5.0]))
    bad["F"] = ContactInput(np.array([R - 0.003, 0.0, 0.0]), np.array([np.inf, 0.0, 0.0]))
    out = world.tick(bad)
    reference.tick(good)
    assert np.array_equal(world.vertices, reference.vertices)  # neither bad user pushed
    assert set(out) == {"A", "N", "F"}
    assert np.all(np.isfinite(out["N"].proxy)) and np.isfinite(out["N"].k_o)
    assert out["F"].in_contact  # its probe was fine: it still gets its local model
    assert np.all(np.isfinite(world.vertices))


def test_a_user_far_away_does_not_push_and_is_not_coupled(world):
    far = ContactInput(np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 3.0]))
    near = ContactInput(np.array([R - 0.002, 0.0, 0.0]), NO_FORCE)
    out = world.tick({"far": far, "near": near})
    assert np.all(world.vertices == world.obj.rest_vertices)
    assert not out["far"].in_contact
    assert out["far"].penetration_m == pytest.approx(-0.4, abs=1e-3)
    assert out["far"].k_o_eff == out["far"].k_o == out["far"].k_o_stiff
    assert out["near"].k_o_eff == pytest.approx(out["near"].k_o)
    assert out["near"].k_o_stiff == pytest.approx(out["near"].k_o)


def test_a_pulling_force_does_not_pull_the_surface_out(world):
    out = world.tick(
        {"A": ContactInput(np.array([0.0, 0.0, R - 0.002]), np.array([0.0, 0.0, -2.0]))}
    )
    assert np.all(world.vertices == world.obj.rest_vertices)
    assert out["A"].in_contact


def test_outputs_and_state_the_room_relies_on(world):
    assert world.vertices.shape == (2562, 3) and world.vertices.dtype == np.float64
    assert world.faces.dtype == np.int32 and world.faces.shape == (5120, 3)
    assert world.n_vertices == 2562 and world.tick_count == 0
    assert np.allclose(world.rest_center, 0.0, atol=1e-12)
    assert world.rest_radius_m == pytest.approx(R)
    assert world.rest_bounds[1, 2] == pytest.approx(R)
    out = world.tick(
        {"x": ContactInput(np.array([0.0, 0.0, R - 0.001]), np.array([0.0, 0.0, 0.5]))}
    )
    assert world.tick_count == 1
    o = out["x"]
    assert isinstance(o.primitive, Plane)
    assert len(o.proxy) == 3 and np.asarray(o.normal) @ [0.0, 0.0, 1.0] > 0.99
    assert 200.0 < o.k_o < 1000.0 and o.k_o_eff == pytest.approx(o.k_o) and o.b_o == 0.0
    assert world.tick({}) == {}
    with pytest.raises(ValueError):
        world.vertices[0, 0] = 1.0


def test_sphere_primitive_matches_the_balloon_curvature():
    world = World(Balloon(), primitive="sphere")
    out = world.tick({"s": ContactInput(np.array([0.05, 0.0, 0.085]), NO_FORCE)})["s"]
    assert isinstance(out.primitive, Sphere)
    assert out.primitive.radius == pytest.approx(R, rel=0.05)
    with pytest.raises(ValueError, match="primitive"):
        World(Balloon(), primitive="cube")  # type: ignore[arg-type]


def test_bench_returns_json_able_timings():
    result = bench_world(n_vertices_list=(642,), users_list=(1, 3), ticks=4, warmup=1)
    text = json.dumps(result)
    assert "median_ms" in text
    runs = result["meshes"][0]["runs"]
    assert [r["users"] for r in runs] == [1, 3]
    # every run measured its ticks (a broken timer would give 0 or NaN); the sizes are not judged
    assert all(0.0 < r["median_ms"] < 1e4 and math.isfinite(r["p99_ms"]) for r in runs)
    assert all(0.0 < r["cpu_median_ms"] < 1e4 for r in runs)  # the CPU clock read too
    assert result["meshes"][0]["build_s"] > 0.0
    with pytest.raises(ValueError, match="icosphere"):
        bench_world(n_vertices_list=(1000,), users_list=(1,), ticks=1)


class RestUser(PUser):
    """A user alone rendering the rest plane the World sends (K_h = K_o, no compensation) where
    it gets one, the current surface with ``fraction`` K_o otherwise."""

    def update(self, out: SurfacePatch) -> None:
        if out.rest_plane is None:
            super().update(out)
            return
        e, nx, ny, nz = out.rest_plane.contact(*(float(c) for c in self.probe))
        self.magnitude = out.k_o * max(e, 0.0)
        self.force = self.magnitude * np.array([nx, ny, nz])


def test_a_user_alone_gets_the_rest_surface_and_feels_the_object_stiffness_there(world):
    # 3 mm into the top of the balloon: the surface gives way under the push, the rest plane
    # stays where the top was, tangent to it, and K_o times the depth under it is the force the
    # object holds the probe with (the surface sits F / K_o in)
    a = RestUser([0.0, 0.0, R - 0.003])
    out = run(world, {"A": a}, 40)["A"]
    rest = out.rest_plane
    assert rest is not None
    assert rest.point[2] == pytest.approx(R, abs=2e-4)
    assert rest.normal == pytest.approx((0.0, 0.0, 1.0), abs=0.02)
    assert out.primitive.point[2] < R - 0.0005  # the current surface gave way
    depth_surface = R - out.proxy[2]
    assert depth_surface == pytest.approx(a.magnitude / out.k_o, rel=0.15)


def test_the_rest_plane_is_withheld_while_another_user_is_in_the_room(world):
    # a user alone gets it; with another user anywhere (even 5 cm under the bottom, neither
    # near nor pushing) neither does: each renders the simulation's surface and feels the
    # other's pushes through it, with no switch when the other comes near
    a = RestUser([0.0, 0.0, R - 0.002])
    out = run(world, {"A": a}, 5)
    assert out["A"].rest_plane is not None
    far = PUser([0.0, 0.0, -R - 0.05])
    out = run(world, {"A": a, "far": far}, 5)
    assert out["A"].rest_plane is None and out["far"].rest_plane is None
    # when the other user has gone, it comes back
    out = run(world, {"A": a}, 1)
    assert out["A"].rest_plane is not None
