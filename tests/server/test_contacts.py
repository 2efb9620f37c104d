"""Contact geometry on the current surface and multipoint stability (DESIGN section 6)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from haptic_collab.server.contact_stiffness import (
    K_O_MAX,
    effective_stiffness,
    spectral_radius,
    stiff_stiffness,
)
from haptic_collab.server.contacts import SurfaceIndex, closest_point, fit_plane, fit_sphere
from haptic_collab.server.objects.balloon import Balloon
from haptic_collab.shared.primitives import Plane, Sphere

R = 0.1


@pytest.fixture
def balloon() -> Balloon:
    return Balloon()


def brute_force_distance(vertices: np.ndarray, faces: np.ndarray, probe: np.ndarray) -> float:
    """Distance from probe to the mesh by testing every triangle (trimesh's own routine)."""
    tris = vertices[faces]
    points = trimesh.triangles.closest_point(tris, np.repeat(probe[None, :], len(tris), axis=0))
    return float(np.min(np.linalg.norm(points - probe, axis=1)))


def test_probe_outside_and_inside_the_rest_balloon(balloon):
    index = SurfaceIndex.build(balloon.rest_vertices, balloon.faces)
    outside = closest_point(index, balloon.vertices, np.array([0.0, 0.0, R + 0.005]), 0.0)
    assert outside.penetration_m == pytest.approx(-0.005, abs=2e-4)
    assert outside.normal @ [0.0, 0.0, 1.0] > 0.999
    assert np.linalg.norm(outside.point) == pytest.approx(R, abs=2e-4)
    direction = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    inside = closest_point(index, balloon.vertices, (R - 0.003) * direction, 0.0)
    assert inside.penetration_m == pytest.approx(0.003, abs=2e-4)
    assert inside.normal @ direction > 0.999


def test_closest_point_is_exact_on_a_deformed_surface(balloon):
    keys = [balloon.patch_key([0, 0, R]), balloon.patch_key([R, 0, 0])]
    balloon.step(keys, [4.0, 2.0])  # a deep dent at the top, a shallower one at the side
    assert balloon.max_displacement_m > 0.01
    index = SurfaceIndex.build(balloon.rest_vertices, balloon.faces)
    current = balloon.vertices
    rng = np.random.default_rng(1)
    probes = [
        np.array([0.0, 0.0, R - 0.015]),
        np.array([0.004, 0.0, R - 0.008]),
        np.array([R - 0.004, 0.0, 0.0]),
    ]
    directions = rng.normal(size=(20, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    probes += list(directions * rng.uniform(R - 0.02, R + 0.02, (20, 1)))
    for probe in probes:
        s = closest_point(index, current, probe, balloon.max_displacement_m)
        exact = brute_force_distance(current, balloon.faces, probe)
        assert abs(s.penetration_m) == pytest.approx(exact, abs=1e-9)
        assert np.linalg.norm(s.point - probe) == pytest.approx(exact, abs=1e-9)
    # the deepest probe, 15 mm under the rest top, is still inside the dented surface
    deep = closest_point(index, current, probes[0], balloon.max_displacement_m)
    assert 0.0 < deep.penetration_m < 0.015


def test_closest_point_refuses_a_nan_probe(balloon):
    index = SurfaceIndex.build(balloon.rest_vertices, balloon.faces)
    with pytest.raises(ValueError, match="finite"):
        closest_point(index, balloon.vertices, np.array([np.nan, 0, 0]), 0.0)


def test_plane_primitive_is_tangent_and_renders_the_same_penetration(balloon):
    index = SurfaceIndex.build(balloon.rest_vertices, balloon.faces)
    probe = np.array([0.03, 0.02, 0.092])
    s = closest_point(index, balloon.vertices, probe, 0.0)
    plane = fit_plane(s)
    assert isinstance(plane, Plane)
    assert plane.penetration(*probe) == pytest.approx(s.penetration_m, abs=1e-5)
    assert plane.penetration(*s.point) == pytest.approx(0.0, abs=1e-12)


def test_sphere_fit_recovers_the_balloon_radius(balloon):
    index = SurfaceIndex.build(balloon.rest_vertices, balloon.faces)
    probe = np.array([0.02, -0.03, 0.09])
    s = closest_point(index, balloon.vertices, probe, 0.0)
    prim = fit_sphere(s, index, balloon.vertices, 0.015, 0.0)
    assert isinstance(prim, Sphere)
    assert prim.radius == pytest.approx(R, rel=0.05)
    assert prim.penetration(*probe) == pytest.approx(s.penetration_m, abs=2e-4)


def test_sphere_fit_falls_back_to_a_plane_in_a_dent_and_on_a_flat_face(balloon):
    balloon.step([balloon.patch_key([0, 0, R])], [3.0])
    index = SurfaceIndex.build(balloon.rest_vertices, balloon.faces)
    s = closest_point(
        index, balloon.vertices, np.array([0.0, 0.0, R - 0.012]), balloon.max_displacement_m
    )
    prim = fit_sphere(s, index, balloon.vertices, 0.008, balloon.max_displacement_m)
    assert isinstance(prim, Plane)  # the bottom of the dent is concave
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide().subdivide().subdivide()
    box_index = SurfaceIndex.build(box.vertices, box.faces)
    s = closest_point(box_index, box.vertices, np.array([0.01, 0.02, 0.098]), 0.0)
    assert isinstance(fit_sphere(s, box_index, box.vertices, 0.02, 0.0), Plane)


def test_uncoupled_contacts_keep_their_stiffness():
    c = np.diag([1 / 300.0, 1 / 500.0])
    k_o = 1 / np.diag(c)
    assert np.allclose(effective_stiffness(c, k_o), k_o)
    assert spectral_radius(c, 0.95 * k_o) == pytest.approx(0.95)


def test_effective_stiffness_guarantees_stability_for_any_smaller_gains():
    rng = np.random.default_rng(3)
    for _ in range(50):
        m = int(rng.integers(2, 7))
        a = rng.normal(size=(m, m))
        c = (a @ a.T + 0.1 * np.eye(m)) * 1e-3  # a random compliance [m/N]
        k_o = 1.0 / np.diag(c)
        k_eff = effective_stiffness(c, k_o)
        assert np.all(k_eff <= k_o * (1 + 1e-12))
        assert spectral_radius(c, k_eff) == pytest.approx(1.0)
        k_h = k_eff * rng.uniform(0.0, 0.999, m)
        assert spectral_radius(c, k_h) < 1.0


def test_bad_compliance_inputs_are_refused():
    with pytest.raises(ValueError, match="compliance must be"):
        effective_stiffness(np.eye(3), [1.0, 2.0])
    with pytest.raises(ValueError, match="finite"):
        effective_stiffness(np.eye(2), [1.0, np.nan])
    with pytest.raises(ValueError, match=">= 0"):
        spectral_radius(np.eye(2), [1.0, -2.0])


def slow_loop(c: np.ndarray, k_h: np.ndarray, x_h: np.ndarray, ticks: int) -> np.ndarray:
    """The coupled slow loop of DESIGN section 6: x(k+1) = C diag(K_h) (x_h - x(k))."""
    x = np.zeros(len(k_h))
    history = []
    for _ in range(ticks):
        x = c @ (k_h * (x_h - x))
        history.append(x.copy())
    return np.array(history)


def test_two_close_contacts_are_unstable_at_095_k_o_but_stable_at_095_k_o_eff(balloon):
    # two fingers 2 cm apart on the top: their 1.5 cm patches overlap
    keys = [balloon.patch_key([0.0, -0.01, 0.0995]), balloon.patch_key([0.0, 0.01, 0.0995])]
    assert keys[0] != keys[1]
    c = balloon.contact_compliance(keys)
    assert c[0, 1] / np.sqrt(c[0, 0] * c[1, 1]) > 0.5  # strongly coupled
    k_o = 1.0 / np.diag(c)
    k_eff = effective_stiffness(c, k_o)
    assert np.all(k_eff < 0.7 * k_o)
    naive, safe = 0.95 * k_o, 0.95 * k_eff
    assert spectral_radius(c, naive) > 1.0
    assert spectral_radius(c, safe) < 1.0

    # in time: both probes held 5 mm under the rest surface
    x_h = np.array([0.005, 0.005])
    diverging = slow_loop(c, naive, x_h, 300)
    settling = slow_loop(c, safe, x_h, 300)
    assert np.abs(diverging[-1]).max() > 1.0  # metres: the surface flies off
    final = np.linalg.solve(np.eye(2) + c * safe, c @ (safe * x_h))
    assert np.allclose(settling[-1], final, rtol=1e-6)
    assert np.all(settling[-1] > 0.0) and np.all(settling[-1] < x_h)

    # the same with the real balloon: forces f_i = K_h,i (x_h,i - x_i) along the normals
    def run_balloon(k_h: np.ndarray, ticks: int) -> list[float]:
        balloon.reset()
        f = np.zeros(2)
        amplitude = []
        for _ in range(ticks):
            balloon.step(keys, f)
            x = np.array(
                [
                    balloon.patch(k).weights @ -balloon.displacement[balloon.patch(k).indices]
                    for k in keys
                ]
            )
            f = k_h * (x_h - x)
            amplitude.append(float(np.abs(x).max()))
        return amplitude

    unstable = run_balloon(naive, 200)
    stable = run_balloon(safe, 200)
    assert unstable[-1] > 100 * unstable[10]  # growing oscillation
    assert stable[-1] == pytest.approx(float(np.abs(final).max()), rel=1e-4)


def test_stiff_stiffness_is_the_stiffest_mode_of_each_coupled_group() -> None:
    from haptic_collab.shared.coupled_compliance import compliance_matrix, modal_stiffness

    k_o = 300.0
    for c in (0.0, 0.5, 0.9):
        cm = compliance_matrix(k_o, c, users=2)
        got = stiff_stiffness(cm, [k_o, k_o])
        assert got == pytest.approx([k_o / (1.0 - c)] * 2)
    # a rigid mode (users pushing the same point) is capped, never infinite or negative
    rigid = stiff_stiffness(np.full((2, 2), 1.0 / k_o), [k_o, k_o])
    assert np.all(rigid == K_O_MAX)
    # two groups: one coupled pair and a lone contact, which keeps its K_o
    cm = np.zeros((3, 3))
    cm[:2, :2] = compliance_matrix(k_o, 0.9, users=2)
    cm[2, 2] = 1.0 / 500.0
    got = stiff_stiffness(cm, [k_o, k_o, 500.0])
    assert got[2] == pytest.approx(500.0)
    assert got[:2] == pytest.approx(modal_stiffness(cm[:2, :2]).k_o_stiff)


def test_interleaved_coupled_groups_are_stabilised_separately() -> None:
    from haptic_collab.shared.coupled_compliance import compliance_matrix

    # contacts 0 and 2 share one dent, 1 and 3 another, 4 is alone: a group's stiffness must
    # not depend on the other contacts, wherever they sit in the list
    pair_a = compliance_matrix(300.0, 0.9, users=2)
    pair_b = compliance_matrix(500.0, 0.5, users=2)
    cm = np.zeros((5, 5))
    cm[np.ix_([0, 2], [0, 2])] = pair_a
    cm[np.ix_([1, 3], [1, 3])] = pair_b
    cm[4, 4] = 1.0 / 800.0
    k_o = 1.0 / np.diag(cm)
    for stiffness in (effective_stiffness, stiff_stiffness):
        got = stiffness(cm, k_o)
        assert got[[0, 2]] == pytest.approx(stiffness(pair_a, k_o[[0, 2]]))
        assert got[[1, 3]] == pytest.approx(stiffness(pair_b, k_o[[1, 3]]))
        assert got[4] == pytest.approx(800.0)
    k_eff = effective_stiffness(cm, k_o)
    assert np.all(k_eff[:4] < k_o[:4])  # both pairs are coupled, hence softened
    assert spectral_radius(cm, 0.99 * k_eff) < 1.0
