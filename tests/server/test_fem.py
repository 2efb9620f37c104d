"""The FEM solid (--object fem): a known answer, the admittance interface, dynamics, bad input.

What a user would notice: a block pressed by the 15 mm finger pad is as stiff as an elastic
solid of its material (the rigid flat punch, K = 2 a E / (1 - nu^2)), twice as stiff when E
doubles; a user pressing one side moves the surface under another; a solid with mass takes
time to give way and settles where the static solid is at once; bad materials and meshes are
refused with one line before anything is built.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from pydantic import ValidationError

from haptic_collab.server.materials import MaterialError
from haptic_collab.server.objects import fem
from haptic_collab.server.objects.fem import FemParams, FemSolid
from haptic_collab.server.objects.fem_elements import (
    element_lumped_mass,
    p2_stiffness_matrix,
    quadratic_mesh,
)
from haptic_collab.server.objects.mesh import MeshError, refine_mesh
from haptic_collab.server.objects.shapes import stress_mesh
from haptic_collab.server.objects.volume import check_volume_mesh, volume_mesh
from haptic_collab.server.solid_materials import (
    SOLID_PRESETS,
    load_solid_material,
    solid_to_params,
)
from haptic_collab.server.world import ContactInput, World
from tests.support.skfem_p2p0 import p2p0_stiffness


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("volumes"))


@pytest.fixture(scope="module")
def block():
    """A 0.12 x 0.12 x 0.06 m block, edges at most 6 mm, its top at z = +0.03 m."""
    return refine_mesh(trimesh.creation.box(extents=(0.12, 0.12, 0.06)), 0.006)


@pytest.fixture(scope="module")
def ball():
    """r = 5 cm, 162 vertices: its P2 solid shows 642 (each face split in four)."""
    return trimesh.creation.icosphere(2, 0.05)


def _top_stiffness(solid: FemSolid) -> float:
    key = solid.patch_key([0.0, 0.0, 0.03], normal=[0.0, 0.0, 1.0])
    return float(solid.contact_stiffness([key])[0])


def test_a_block_pressed_by_the_finger_pad_is_as_stiff_as_a_flat_punch_and_scales_with_e(
    block, cache, caplog
):
    params = FemParams(young_pa=5.0e3, poisson=0.3, n_modes=0)
    with caplog.at_level("INFO", logger="haptic.server.fem"):
        solid = FemSolid(block, params, cache_dir=cache)
    # about 65000 P2 nodes: linear elements with averaged nodal pressure, the surface shown as
    # given, and the log says so
    assert solid.element == "anp" and solid.n_vertices == len(block.vertices)
    assert "linear tetrahedra with averaged nodal pressure" in caplog.text
    k = _top_stiffness(solid)
    punch = 2.0 * params.patch_radius_m * params.young_pa / (1.0 - params.poisson**2)
    # a finite block fixed at its bottom and 6 mm linear elements are stiffer than the
    # half-space (docs/fem.md: 1.38 here, 1.19 for a 0.2 m block at 5 mm)
    assert 1.0 <= k / punch <= 1.5
    stiffer = FemSolid(block, replace(params, young_pa=10.0e3), cache_dir=cache)
    assert _top_stiffness(stiffer) == pytest.approx(2.0 * k, rel=1e-9)


def test_the_assembly_agrees_with_scikit_fem(ball, cache):
    """The quadratic (P2) stiffness is scikit-fem's P2 elasticity with a constant pressure on each
    element (P2/P0, condensed) on the same mesh, dof by dof, and softer than plain P2 (less
    energy for every displacement); the HRZ masses are positive and each element's mass; the
    consistent mass's diagonal (the HRZ shares) is scikit-fem's."""
    skfem = pytest.importorskip("skfem")
    from scipy.spatial import cKDTree
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    nodes, tets = volume_mesh(ball.vertices, ball.faces, cache_dir=cache)
    lam, mu = lame_parameters(5.0e3, 0.45)
    nodes2, elements, _, _ = quadratic_mesh(nodes, tets, np.asarray(ball.faces))
    ours = p2_stiffness_matrix(nodes2, elements, lam, mu)
    element = skfem.ElementVector(skfem.ElementTetP2())
    basis = skfem.Basis(skfem.MeshTet(nodes.T, tets.T), element)
    theirs = p2p0_stiffness(basis, lam, mu)
    # their dofs by location and axis: the axis from the vector element's component of each dof
    dist, node = cKDTree(nodes2).query(basis.doflocs.T)
    assert dist.max() < 1e-12
    axis = np.empty(basis.N, dtype=np.int64)
    for k in range(3):
        unit = basis.project(
            lambda x, k=k: np.stack([np.full_like(x[0], float(i == k)) for i in range(3)])
        )
        axis[np.isclose(unit, 1.0)] = k
    order = np.argsort(3 * node + axis)  # their dof of our dof 3 node + axis
    diff = abs(ours - theirs[order][:, order]).max()
    assert diff <= 1e-9 * abs(ours).max()
    plain = skfem.asm(linear_elasticity(lam, mu), basis)[order][:, order]
    # plain P2's volumetric energy exceeds the mean dilatation's (Jensen's inequality, per element)
    u = np.random.default_rng(0).normal(size=(10, ours.shape[0]))
    assert np.all(np.einsum("ki,ki->k", u @ (plain - ours).T, u) > 0.0)
    masses = element_lumped_mass(nodes2, elements, 1000.0)
    assert masses.min() > 0.0
    assert masses.sum() == pytest.approx(1000.0 * ball.volume, rel=1e-9)
    # HRZ: the consistent mass's diagonal scaled to the element's mass (by 70 / 36 for a
    # straight-sided P2 tetrahedron), so each node's lumped mass is that scale of scikit-fem's
    scalar = skfem.Basis(skfem.MeshTet(nodes.T, tets.T), skfem.ElementTetP2())
    diagonal = skfem.asm(skfem.BilinearForm(lambda u, v, w: u * v), scalar).diagonal()
    _, at = cKDTree(nodes2).query(scalar.doflocs.T)
    assert masses[at] == pytest.approx(1000.0 * 70.0 / 36.0 * diagonal, rel=1e-9)


def test_the_volume_mesh_keeps_the_surface_and_the_server_never_imports_tetgen(ball, cache):
    """The P2 solid shows its surface split four ways: the mesh's vertices first, unchanged,
    then its edges' midpoints; every face in four, outward, the same area."""
    solid = FemSolid(ball, FemParams(n_modes=0), cache_dir=cache)
    assert solid.element == "p2"
    n = len(ball.vertices)
    assert np.array_equal(solid.nodes[:n], ball.vertices)
    assert solid.n_vertices == n + len(ball.edges_unique)  # 162 + 480 = 642
    assert len(solid.nodes) > solid.n_vertices  # interior nodes
    assert len(solid.faces) == 4 * len(ball.faces)
    mids = 0.5 * ball.vertices[ball.edges_unique].sum(axis=1)
    assert np.allclose(np.sort(solid.rest_vertices[n:], axis=0), np.sort(mids, axis=0))
    shown = trimesh.Trimesh(solid.rest_vertices, solid.faces, process=False)
    assert shown.is_watertight and shown.volume == pytest.approx(ball.volume, rel=1e-12)
    assert "tetgen" not in sys.modules


def test_a_cached_volume_mesh_is_used_without_tetgen(ball, cache, monkeypatch):
    volume_mesh(ball.vertices, ball.faces, cache_dir=cache)

    def no_child(*args, **kwargs):
        raise AssertionError("TetGen ran although the volume mesh was cached")

    monkeypatch.setattr(subprocess, "run", no_child)
    nodes, _ = volume_mesh(ball.vertices, ball.faces, cache_dir=cache)
    assert len(nodes) > len(ball.vertices)


def test_a_cached_volume_mesh_with_an_interior_node_moved_is_refused_and_rebuilt(
    ball, tmp_path, caplog
):
    """The surface check cannot see an interior node moved: the whole mesh's hash does."""
    folder = tmp_path / "volumes"
    nodes, tets = volume_mesh(ball.vertices, ball.faces, cache_dir=folder)
    (path,) = folder.glob("*.npz")
    with np.load(path) as data:
        stored = {key: data[key] for key in data.files}
    interior = len(ball.vertices)  # the first node after the surface's vertices
    stored["nodes"][interior] += [0.5, 0.0, 0.0]
    np.savez(path, **stored)
    with caplog.at_level("WARNING", logger="haptic_collab.server.objects.volume"):
        again, again_tets = volume_mesh(ball.vertices, ball.faces, cache_dir=folder)
    assert "refused" in caplog.text and "do not match" in caplog.text
    assert np.array_equal(again, nodes) and np.array_equal(again_tets, tets)  # TetGen's own
    with np.load(path) as data:  # and the cache holds the rebuilt mesh again
        assert np.array_equal(data["nodes"], nodes)


def test_a_push_moves_the_surface_under_another_user(ball, cache):
    solid = FemSolid(ball, FemParams(n_modes=0), cache_dir=cache)
    top = solid.patch_key([0.0, 0.0, 0.05], normal=[0, 0, 1])
    side = solid.patch_key([0.05, 0.0, 0.0], normal=[1, 0, 0])
    near = solid.patch_key([0.0, 0.02, 0.046], normal=[0, 0.4, 0.9])
    c = solid.contact_compliance([top, side, near])
    assert np.allclose(c, c.T)
    assert np.all(np.linalg.eigvalsh(c) > 0.0)
    # a contact 2 cm from the top feels much of the top's push, the side less
    assert c[0, 2] > 0.2 * c[0, 0]
    assert abs(c[0, 1]) < c[0, 2]
    before = solid.vertices[solid.patch(near).indices].mean(axis=0)
    solid.step([top], [1.0])
    after = solid.vertices[solid.patch(near).indices].mean(axis=0)
    assert np.linalg.norm(after - before) > 1e-4  # 1 N on the top moves a point 2 cm away


def test_a_solid_with_mass_lags_and_rings_then_settles_where_the_static_one_is(ball, cache):
    """A soft gel ball (E 1 kPa, lowest mode 1.5 Hz) under a held 0.5 N push, 20 Hz ticks."""
    static = FemSolid(ball, FemParams(young_pa=1.0e3, n_modes=0), cache_dir=cache)
    dynamic = FemSolid(
        ball, FemParams(young_pa=1.0e3, n_modes=24, rayleigh_beta=0.02), cache_dir=cache
    )
    key = static.patch_key([0.0, 0.0, 0.05], normal=[0, 0, 1])
    assert dynamic.patch_key([0.0, 0.0, 0.05], normal=[0, 0, 1]) == key
    idx = static.patch(key).indices

    def depth(solid: FemSolid) -> float:
        return float(0.05 - solid.vertices[idx, 2].mean())

    static.step([key], [0.5])
    track = []
    for _ in range(60):  # 3 s
        dynamic.step([key], [0.5])
        track.append(depth(dynamic) / depth(static))
    assert 1.0 < dynamic.natural_frequencies_hz[0] < 3.0
    assert track[0] < 0.9  # inertia: not there in the first tick
    assert max(track) > 1.05  # it overshoots and rings
    assert track[-1] == pytest.approx(1.0, abs=0.01)  # and settles at the static dent
    assert dynamic.contact_damping([key])[0] > 0.0  # the mass holds the first tick back: B_o
    assert static.contact_damping([key])[0] == 0.0


def test_the_fem_solid_runs_in_the_world_with_two_users(ball, cache):
    """Two probes held in the ball, each pushed back by half its K_o_eff (a slow-loop stable
    coupling): both settle in contact, the object's stiffness reported where the design needs it."""
    world = World(FemSolid(ball, FemParams(n_modes=8), cache_dir=cache))
    probes = {"A": np.array([0.0, 0.0, 0.047]), "B": np.array([0.047, 0.0, 0.0])}
    force = {"A": np.zeros(3), "B": np.zeros(3)}
    depths: dict[str, list[float]] = {"A": [], "B": []}
    for _ in range(60):
        out = world.tick({u: ContactInput(probe=probes[u], force=force[u]) for u in probes})
        for u in probes:
            force[u] = (
                np.asarray(out[u].normal) * 0.5 * out[u].k_o_eff * max(out[u].penetration_m, 0.0)
            )
            depths[u].append(out[u].penetration_m)
    for u in probes:
        last = np.array(depths[u][-10:])
        assert np.all(last > 0.0)  # in contact
        assert np.ptp(last) < 1e-4  # settled, not oscillating
        assert 10.0 < out[u].k_o < 1.0e4
        assert out[u].k_o_eff <= out[u].k_o + 1e-9
        assert np.all(np.isfinite(out[u].proxy))


@pytest.mark.parametrize(
    "field, value",
    [("poisson", 0.5), ("poisson", -1.0), ("poisson", 0.7), ("young_pa", 0.0), ("young_pa", -5.0)],
)
def test_impossible_materials_are_refused_by_name(field, value):
    with pytest.raises(ValidationError, match=field):
        FemParams(**{field: value})


def test_a_material_file_needs_its_numbers_and_their_source(tmp_path):
    good = tmp_path / "phantom.toml"
    good.write_text('young_pa = 20000.0\npoisson = 0.45\ndensity_kg_m3 = 1000.0\nsource = "lab"\n')
    material = load_solid_material(good)
    assert material.name == "phantom" and material.young_pa == 20000.0
    assert solid_to_params(material, FemParams()).young_pa == 20000.0
    bad = tmp_path / "bad.toml"
    bad.write_text('young_pa = 20000.0\npoisson = 0.5\ndensity_kg_m3 = 1000.0\nsource = "lab"\n')
    with pytest.raises(MaterialError, match="poisson"):
        load_solid_material(bad)
    unsourced = tmp_path / "unsourced.toml"
    unsourced.write_text("young_pa = 20000.0\npoisson = 0.45\ndensity_kg_m3 = 1000.0\n")
    with pytest.raises(MaterialError, match="source"):
        load_solid_material(unsourced)
    with pytest.raises(MaterialError, match="liver"):
        load_solid_material("livr")
    assert set(SOLID_PRESETS) >= {"liver", "skin", "ecoflex-0030", "sylgard-184"}


def test_a_degenerate_or_foreign_volume_mesh_is_refused(ball, cache):
    nodes, tets = volume_mesh(ball.vertices, ball.faces, cache_dir=cache)
    flat = tets.copy()
    flat[0] = [flat[0][0], flat[0][0], flat[0][1], flat[0][2]]
    with pytest.raises(MeshError, match="degenerate"):
        check_volume_mesh(nodes, flat, ball.vertices)
    moved = nodes.copy()
    moved[0] += 1e-3
    with pytest.raises(MeshError, match="surface vertices"):
        check_volume_mesh(moved, tets, ball.vertices)
    with pytest.raises(MeshError, match="degenerate"):
        FemSolid(ball, FemParams(n_modes=0), volume=(nodes, flat))


def test_a_surface_that_cannot_be_tetrahedralised_is_one_clear_error(tmp_path):
    """Two overlapping spheres (self-intersecting): TetGen fails or crashes, the server does not."""
    a = trimesh.creation.icosphere(2, 0.05)
    b = a.copy()
    b.apply_translation([0.04, 0.0, 0.0])
    both = trimesh.util.concatenate([a, b])
    with pytest.raises(MeshError, match="tetrahedralised"):
        volume_mesh(both.vertices, both.faces, cache_dir=str(tmp_path))


def test_haptic_bench_server_reports_the_fem_start_up_and_tick_cost():
    from haptic_collab.bench.world import bench_fem

    result = bench_fem(n_vertices_list=(642,), users=2, ticks=4, warmup=1)
    (row,) = result["meshes"]
    assert row["n_vertices"] == 642 and row["nodes"] > 642
    for key in ("volume_mesh_s", "assembly_s", "factor_s", "modes_s", "median_ms", "p99_ms"):
        assert row[key] > 0.0
    with pytest.raises(ValueError, match="icosphere"):
        bench_fem(n_vertices_list=(1000,))


@pytest.fixture(scope="module")
def bar():
    """A 4 x 4 x 20 cm liver bar standing on its end (fixed at its lowest fifth), 1 cm edges."""
    mesh = trimesh.creation.box(extents=(0.04, 0.04, 0.2))
    mesh.apply_translation((0.0, 0.0, 0.1))
    return refine_mesh(mesh, 0.01)


@pytest.mark.parametrize("push_n", [0.025, 0.05])
def test_a_bar_bent_by_centimetres_keeps_its_volume_and_its_tip_swings_down(bar, cache, push_n):
    """A sideways push near the top bends the bar 2-4 cm. The linear model moves the tip
    straight sideways and stretches the bar (its volume grows by percents); modal warping
    carries each part along its rotation: the tip follows an arc and the volume is kept."""
    results = {}
    for warp in (False, True):
        solid = FemSolid(bar, FemParams(density_kg_m3=0.0, warp=warp), cache_dir=cache)
        key = solid.patch_key([0.02, 0.0, 0.18], normal=[1.0, 0.0, 0.0])
        solid.step([key], [push_n])
        verts = solid.vertices
        tip = int(np.argmax(bar.vertices[:, 2] - 1e-3 * bar.vertices[:, 0]))
        growth = trimesh.Trimesh(verts, solid.faces).volume / bar.volume - 1.0
        results[warp] = (growth, verts[tip] - bar.vertices[tip])
    (linear_growth, linear_tip), (warped_growth, warped_tip) = results[False], results[True]
    assert linear_tip[0] < -0.02  # bent by centimetres (pushed towards -x)
    assert linear_growth > 0.01  # the linear model grows the bar by more than 1 %
    assert abs(warped_growth) < 0.2 * linear_growth  # warping keeps the volume
    assert warped_tip[2] < linear_tip[2] - 0.001  # the tip swings down along an arc


def test_warping_leaves_a_small_press_as_the_linear_model_has_it(ball, cache):
    linear = FemSolid(ball, FemParams(density_kg_m3=0.0, warp=False), cache_dir=cache)
    warped = FemSolid(ball, FemParams(density_kg_m3=0.0), cache_dir=cache)
    key = linear.patch_key([0.0, 0.0, 0.05], normal=[0, 0, 1])
    for solid in (linear, warped):
        solid.step([key], [0.2])  # about 1 mm
    d_lin, d_warp = linear.displacement, warped.displacement
    assert np.abs(d_warp - d_lin).max() < 0.02 * np.abs(d_lin).max()
    assert warped.contact_stiffness([key])[0] == linear.contact_stiffness([key])[0]


def test_a_bent_part_is_loaded_at_its_own_patch(bar, cache):
    """A user pressing the side of the bar near its top bends it by centimetres and follows it:
    the push stays on the patch of the material under the finger (patch centres are rest
    positions), not on whichever rest patch is now nearest in space."""
    solid = FemSolid(bar, FemParams(density_kg_m3=0.0), cache_dir=cache)
    world = World(solid)
    spacing = solid.params.patch_spacing_m
    rest_point = np.array([0.02, 0.0, 0.18])
    vertex = int(np.argmin(np.linalg.norm(bar.vertices - rest_point, axis=1)))
    normal = np.array([1.0, 0.0, 0.0])
    for _ in range(12):
        probe = solid.vertices[vertex] - 0.002 * normal
        out = world.tick({"u": ContactInput(probe=probe, force=0.05 * normal)})["u"]
        normal = np.asarray(out.normal)
    assert solid.vertices[vertex][0] - rest_point[0] < -0.03  # bent by centimetres
    key = world._users["u"].key
    assert np.linalg.norm(solid.rest_vertices[key] - rest_point) < 1.5 * spacing


def test_a_small_rigid_turn_is_the_rotation_every_surface_vertex_reports(ball, cache):
    """Modal warping's rotation estimate on P2 elements: a small rigid rotation ``u = w x x``
    (a linear field, which P2 holds exactly) reads back as ``w`` at every surface vertex,
    corners and mid-edge vertices alike."""
    from haptic_collab.server.objects.fem_elements import rotation_operator

    solid = FemSolid(ball, FemParams(n_modes=0), cache_dir=cache)
    n_all = len(solid.nodes)
    op = rotation_operator(solid.nodes, solid.elements, solid.n_vertices, np.arange(3 * n_all))
    w = np.array([0.01, -0.02, 0.005])
    u = np.cross(w, solid.nodes).ravel()
    got = (op @ u).reshape(-1, 3)
    assert np.abs(got - w).max() <= 1e-9 * np.abs(w).max()


def test_the_pad_presses_with_the_flat_punch_pressure_integrated(ball, cache):
    """The P2 punch loads of one unit push: they sum to 1 along the patch normal, their first
    moment is the pad's centre on a symmetric patch, and they reach past the vertices under the
    pad to every face the pad's disc crosses."""
    solid = FemSolid(ball, FemParams(n_modes=0), cache_dir=cache)
    key = solid.patch_key([0.0, 0.0, 0.05], normal=[0.0, 0.0, 1.0])
    pt = solid.patch(key)
    assert pt.weights.sum() == pytest.approx(1.0, abs=1e-12)
    centre = solid.rest_vertices[key]
    first_moment = pt.weights @ (solid.rest_vertices[pt.indices] - centre)
    planar = first_moment - (first_moment @ pt.normal) * pt.normal
    assert np.linalg.norm(planar) < 0.05 * solid.params.patch_radius_m
    across = solid.rest_vertices[pt.indices] - centre
    d = np.linalg.norm(across - np.outer(across @ pt.normal, pt.normal), axis=1)
    assert d.max() > solid.params.patch_radius_m  # nodes of the faces the rim crosses


def test_the_servers_fem_sphere_shows_as_many_vertices_as_the_balloons():
    """``--subdivisions 2``: the balloon's sphere has 162 vertices; the FEM solid is P2 on its
    42-vertex parent and shows 162, on the parent's chords."""
    from haptic_collab.server.main import ServerOptions, build_world

    balloon = build_world(ServerOptions(subdivisions=2))
    solid = build_world(ServerOptions(object="fem", subdivisions=2)).obj
    assert solid.element == "p2"
    assert solid.n_vertices == len(balloon.vertices) == 162
    radius = np.linalg.norm(solid.rest_vertices, axis=1)
    assert radius.max() == pytest.approx(0.1, rel=1e-9) and radius.min() > 0.09


def test_a_push_on_the_torus_side_loads_the_pad_not_the_far_wall_behind_it():
    """On the torus's outer side the pad's cylinder also passes through the ring's far inner
    wall, which faces the same way. Only the surface under the pad may take the push: loaded
    there, the far wall took 54 % of it and the side felt 346 N/m instead of about 255."""
    torus = stress_mesh("torus")
    v = np.asarray(torus.vertices, dtype=np.float64)
    faces = np.asarray(torus.faces, dtype=np.int64)
    mids = v[torus.edges_unique].mean(axis=1)  # P2's mid-edge nodes on straight edges
    e = len(v) + np.asarray(torus.faces_unique_edges, dtype=np.int64)  # edges 01, 12, 20
    nodes = np.vstack([v, mids])
    faces6 = np.column_stack([faces, e])
    key = int(np.argmax(v[:, 0]))  # the outer side, facing +x
    normal = np.asarray(torus.vertex_normals[key], dtype=np.float64)
    a = FemParams().patch_radius_m
    idx, w = fem.p2_punch_loads(nodes, faces6, v[key], normal, a)
    assert w.sum() == pytest.approx(1.0, abs=1e-12)
    far = np.linalg.norm(nodes[idx] - v[key], axis=1) > 2.0 * a
    assert not far.any(), f"{far.sum()} loaded nodes beyond 2 a, {w[far].sum():.0%} of the push"
    # and the push's centre is the pad's
    centre = w @ nodes[idx]
    assert np.linalg.norm(centre - v[key]) < 0.2 * a
