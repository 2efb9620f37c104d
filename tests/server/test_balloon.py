"""The water balloon (DESIGN section 5): stiffness, water coupling, base, damping, numerics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from haptic_collab.server.contact_stiffness import K_O_MAX
from haptic_collab.server.objects.balloon import (
    Balloon,
    BalloonParams,
    cotangent_laplacian,
    vertex_areas,
)
from haptic_collab.server.objects.mesh import MeshError, default_balloon

TOP = np.array([0.0, 0.0, 0.1])
SIDE = np.array([0.1, 0.0, 0.0])


@pytest.fixture
def balloon() -> Balloon:
    return Balloon()  # default: r = 0.1 m, 2562 vertices


def patch_displacement(b: Balloon, key: int) -> float:
    """Inward displacement [m] of a patch: beta^T (-w)."""
    p = b.patch(key)
    return float(-(p.weights @ b.displacement[p.indices]))


def test_contact_stiffness_is_in_the_papers_range_at_top_and_side(balloon):
    k = balloon.contact_stiffness([balloon.patch_key(TOP), balloon.patch_key(SIDE)])
    assert np.all((k > 200.0) & (k < 1000.0)), k


def test_pushing_the_top_bulges_every_equator_point_outward(balloon):
    balloon.step([balloon.patch_key(TOP)], [2.0])
    w = balloon.displacement
    rest = balloon.rest_vertices
    equator = np.abs(rest[:, 2]) < 0.01
    top = int(np.argmax(rest[:, 2]))
    assert w[top] < -0.004  # the top goes in by millimetres
    assert np.all(w[equator] > 0.0)  # and the water pushes the whole equator out
    # the water is nearly incompressible: the volume change is tiny next to the dent's volume
    dent = float(balloon.vertex_areas[w < 0] @ w[w < 0])
    assert abs(balloon.volume_change_m3) < 1e-3 * abs(dent)


def test_top_and_side_contacts_are_coupled_by_about_an_eighth(balloon):
    c = balloon.contact_compliance([balloon.patch_key(TOP), balloon.patch_key(SIDE)])
    assert c[0, 1] == pytest.approx(c[1, 0])
    ratio = -c[0, 1] / c[1, 1]  # pushing the top moves the side *out*: negative cross term
    assert 0.10 < ratio < 0.18, ratio


def test_compliance_predicts_the_displacement_and_is_positive_definite(balloon):
    points = [TOP, SIDE, [0.0, 0.07, 0.07], [0.0, 0.02, 0.098], [-0.06, -0.06, 0.05]]
    keys = [balloon.patch_key(p) for p in points]
    c = balloon.contact_compliance(keys)
    assert np.allclose(c, c.T)
    assert np.linalg.eigvalsh(c).min() > 0.0
    f = np.array([1.0, 0.5, 2.0, 0.0, 1.5])
    balloon.step(keys, f)
    moved = [patch_displacement(balloon, k) for k in keys]
    assert np.allclose(moved, c @ f, rtol=1e-9, atol=1e-12)


def test_response_is_linear_in_the_force(balloon):
    key = balloon.patch_key(TOP)
    balloon.step([key], [1.0])
    one = balloon.displacement
    balloon.step([key], [3.0])
    assert np.allclose(balloon.displacement, 3.0 * one)
    balloon.step([], [])
    assert np.all(balloon.displacement == 0.0)


def test_sherman_morrison_solve_matches_a_dense_solve_of_the_full_stiffness():
    p = BalloonParams()
    b = Balloon(default_balloon(0.1, 2), p)
    verts, faces = b.rest_vertices, b.faces
    a = vertex_areas(verts, faces)
    lap = cotangent_laplacian(verts, faces).toarray()
    k = p.tension * lap + p.bending * lap @ np.diag(1 / a) @ lap + p.foundation * np.diag(a)
    k += p.bulk * np.outer(a, a)
    free = ~b.fixed_mask
    key = b.patch_key(TOP)
    patch = b.patch(key)
    beta = np.zeros(len(verts))
    beta[patch.indices] = patch.weights
    w = np.zeros(len(verts))
    w[free] = np.linalg.solve(k[np.ix_(free, free)], -2.0 * beta[free])
    b.step([key], [2.0])
    assert np.allclose(b.displacement, w, rtol=1e-6, atol=1e-9 * np.abs(w).max())


def test_stiffness_converges_under_mesh_refinement():
    coarse, fine = Balloon(default_balloon(0.1, 4)), Balloon(default_balloon(0.1, 5))
    k_coarse = coarse.contact_stiffness([coarse.patch_key(TOP)])[0]
    k_fine = fine.contact_stiffness([fine.patch_key(TOP)])[0]
    assert k_fine == pytest.approx(k_coarse, rel=0.05)


def test_base_vertices_do_not_move_and_a_push_on_the_base_meets_the_table(balloon):
    fixed = balloon.fixed_mask
    assert 3 <= fixed.sum() < 0.05 * balloon.n_vertices
    assert np.all(balloon.rest_vertices[fixed, 2] < -0.09)
    balloon.step([balloon.patch_key(TOP), balloon.patch_key(SIDE)], [3.0, 1.0])
    assert np.all(balloon.displacement[fixed] == 0.0)
    # a balloon with a wide base: a push right at the bottom meets only fixed vertices
    wide = Balloon(params=BalloonParams(base_radius_m=0.05))
    bottom = wide.patch_key([0.0, 0.0, -0.1])
    assert wide.contact_stiffness([bottom])[0] == K_O_MAX


def test_patch_weights_sum_to_one_within_the_finger_pad(balloon):
    patch = balloon.patch(balloon.patch_key(SIDE))
    assert patch.weights.sum() == pytest.approx(1.0)
    assert np.all(patch.weights > 0.0)
    d = np.linalg.norm(
        balloon.rest_vertices[patch.indices] - balloon.rest_vertices[patch.key], axis=1
    )
    assert d.max() < balloon.params.patch_radius_m
    assert len(patch.indices) > 10  # a finger pad, not a point load


def test_cached_patches_need_no_new_solve(balloon):
    keys = [balloon.patch_key(TOP), balloon.patch_key(SIDE)]
    balloon.contact_compliance(keys)
    solved = balloon.solve_count
    for _ in range(5):
        balloon.step(keys, [1.0, 1.0])
        balloon.contact_compliance(keys)
    assert balloon.solve_count == solved == 2


def test_patch_key_keeps_its_centre_while_the_contact_jitters(balloon):
    key = balloon.patch_key(TOP)
    centre = balloon.rest_vertices[key]
    step = 0.5 * balloon.params.patch_spacing_m
    for dx in (step, -step, 0.3 * step):
        assert balloon.patch_key(centre + [dx, 0.0, 0.0], previous=key) == key
    far = balloon.patch_key(centre + [0.03, 0.0, 0.0], previous=key)
    assert far != key


def test_damping_slows_the_first_tick_to_k_o_plus_b_o_and_settles_to_k_o():
    b = Balloon(params=BalloonParams(damping=2e4))
    key = b.patch_key(TOP)
    k_o = b.contact_stiffness([key])[0]
    b_o = b.contact_damping([key])[0]
    assert b_o > 0.2 * k_o
    b.step([key], [1.0])
    first = patch_displacement(b, key)
    assert first == pytest.approx(1.0 / (k_o + b_o), rel=1e-6)
    moves = [first]
    for _ in range(300):
        b.step([key], [1.0])
        moves.append(patch_displacement(b, key))
    assert np.all(np.diff(moves) > -1e-12)  # creeps in monotonically
    assert moves[-1] == pytest.approx(1.0 / k_o, rel=0.02)


def test_without_damping_b_o_is_zero_and_the_response_is_immediate(balloon):
    key = balloon.patch_key(SIDE)
    assert balloon.contact_damping([key])[0] == 0.0
    balloon.step([key], [1.0])
    assert patch_displacement(balloon, key) == pytest.approx(
        1.0 / balloon.contact_stiffness([key])[0]
    )


def test_a_stiff_foundation_kills_the_water_coupling():
    soft = Balloon()
    stiff = Balloon(params=BalloonParams(foundation=1e6))
    ratios = []
    for b in (soft, stiff):
        c = b.contact_compliance([b.patch_key(TOP), b.patch_key(SIDE)])
        ratios.append(-c[0, 1] / c[1, 1])
    assert ratios[1] < 0.3 * ratios[0]


@pytest.mark.parametrize(
    "field, value",
    [
        ("tension", 0.0),
        ("tension", float("nan")),
        ("bulk", -1.0),
        ("patch_radius_m", 0.0),
        ("sim_period_s", float("inf")),
    ],
)
def test_bad_parameters_are_refused_with_the_field_named(field, value):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(BalloonParams(), **{field: value})


def test_non_finite_force_is_refused_and_leaves_the_state_unchanged(balloon):
    key = balloon.patch_key(TOP)
    balloon.step([key], [1.0])
    before = balloon.displacement
    with pytest.raises(ValueError, match="finite"):
        balloon.step([key], [float("nan")])
    with pytest.raises(ValueError, match="forces"):
        balloon.step([key], [1.0, 2.0])
    assert np.array_equal(balloon.displacement, before)
    with pytest.raises(ValueError, match="finite"):
        balloon.patch_key([np.nan, 0.0, 0.0])


def test_open_or_split_meshes_are_refused():
    cube = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    open_box = trimesh.Trimesh(cube.vertices, cube.faces[:-2], process=False)
    with pytest.raises(MeshError, match="not closed"):
        Balloon(open_box)
    far = default_balloon(0.05, 2)
    far.apply_translation((0.2, 0.0, 0.0))
    near = default_balloon(0.05, 2)
    two = trimesh.Trimesh(
        np.vstack([near.vertices, far.vertices]),
        np.vstack([near.faces, far.faces + len(near.vertices)]),
        process=False,
    )
    with pytest.raises(MeshError, match="2 bodies"):
        Balloon(two)


def test_any_closed_mesh_works_a_box_pushed_on_top_bulges_its_sides():
    box = trimesh.creation.box(extents=(0.15, 0.15, 0.1)).subdivide().subdivide().subdivide()
    b = Balloon(box)
    key = b.patch_key([0.0, 0.0, 0.05])
    k_o = b.contact_stiffness([key])[0]
    assert 10.0 < k_o < K_O_MAX
    b.step([key], [1.0])
    rest, w = b.rest_vertices, b.displacement
    assert w[key] < 0.0
    side = (
        (np.abs(rest[:, 0] - 0.075) < 1e-9)
        & (np.abs(rest[:, 2]) < 0.02)
        & (np.abs(rest[:, 1]) < 0.04)
    )
    assert side.any() and np.all(w[side] > 0.0)
    assert sp.issparse(cotangent_laplacian(rest, b.faces))
