"""Inclusions inside the FEM solid: refusals, the conforming mesh, per-element materials, and what
a palpating user feels (server/objects/inclusions.py, haptic_collab/research/palpation.py)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from haptic_collab.demo_report import STIFFNESS_JND
from haptic_collab.research.palpation import measure, sphere_lump
from haptic_collab.server.materials import MaterialError
from haptic_collab.server.objects.fem_elements import (
    element_gradients,
    lumped_mass,
    stiffness_matrix,
)
from haptic_collab.server.objects.inclusions import (
    Inclusion,
    InclusionError,
    check_inclusions,
    cluster_decimate,
    element_materials,
    inclusion_material,
    inclusion_surfaces,
    load_inclusions,
    mass_by_groups,
    region_boundary,
    stiffness_by_groups,
    volume_with_inclusions,
    winding_number,
)
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.solid_materials import SOLID_PRESETS

LIVER = SOLID_PRESETS["liver"]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("volumes")


@pytest.fixture(scope="module")
def ball():
    return default_balloon(subdivisions=2)  # 0.1 m radius, 162 vertices: P2 shows 642


def _lump(centre, radius, material=None, where="lump", subdivisions=2):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    mesh.apply_translation(centre)
    return Inclusion(mesh=mesh, material=material or inclusion_material("liver*10"), where=where)


def test_the_winding_number_says_inside_and_outside_of_a_closed_surface():
    box = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    w = winding_number([[0.0, 0.0, 0.0], [0.009, -0.009, 0.009], [0.011, 0.0, 0.0], [0.5, 0, 0]],
                       box.vertices, box.faces)  # fmt: skip
    np.testing.assert_allclose(w, [1.0, 1.0, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize(
    ("centre", "radius", "words"),
    [
        ((0.0, 0.0, 0.3), 0.01, "vertices are outside the solid"),  # wholly outside
        ((0.0, 0.0, 0.095), 0.01, "outside the solid"),  # pokes through the top
        ((0.0, 0.0, 0.0), 0.2, "outside the solid"),  # the solid inside the inclusion
    ],
)
def test_an_inclusion_not_inside_the_solid_is_refused_saying_where(ball, centre, radius, words):
    with pytest.raises(InclusionError, match=words) as err:
        check_inclusions(ball, [_lump(centre, radius)])
    assert "lump" in str(err.value)


def test_overlapping_inclusions_are_refused_and_apart_ones_are_not(ball):
    a = _lump((0.0, 0.0, 0.05), 0.01, where="a.stl")
    check_inclusions(ball, [a, _lump((0.0, 0.0, -0.05), 0.01, where="b.stl")])
    with pytest.raises(InclusionError, match=r"a\.stl.*b\.stl.*overlap"):
        check_inclusions(ball, [a, _lump((0.0, 0.0, 0.055), 0.01, where="b.stl")])


def test_an_inclusion_material_is_a_preset_a_scaled_preset_or_refused():
    assert inclusion_material("skin") == SOLID_PRESETS["skin"]
    ten = inclusion_material("liver*10")
    assert ten.young_pa == pytest.approx(10.0 * LIVER.young_pa)
    assert (ten.poisson, ten.density_kg_m3) == (LIVER.poisson, LIVER.density_kg_m3)
    for bad in ("liver*0", "liver*-2", "bone*10", "liver*x"):
        with pytest.raises(MaterialError):
            inclusion_material(bad)


def test_inclusion_files_and_materials_pair_in_order(tmp_path):
    path = tmp_path / "lump.stl"
    trimesh.creation.icosphere(subdivisions=2, radius=0.005).export(path)
    (inc,) = load_inclusions([path], ["liver*5"])
    assert inc.material.young_pa == pytest.approx(5.0 * LIVER.young_pa)
    assert inc.mesh.is_watertight
    with pytest.raises(InclusionError, match="1 --inclusion file.*2 --inclusion-material"):
        load_inclusions([path], ["liver", "skin"])
    with pytest.raises(InclusionError, match="missing.stl"):
        load_inclusions([tmp_path / "missing.stl"], ["liver"])


def test_the_volume_mesh_conforms_to_the_lump_and_keeps_the_surface(ball, cache):
    lump = _lump((0.02, 0.0, 0.07), 0.008)
    nodes, tets = volume_with_inclusions(ball, [lump], cache_dir=cache)
    np.testing.assert_array_equal(nodes[: len(ball.vertices)], ball.vertices)
    mats = element_materials(nodes, tets, LIVER, [lump])
    _, vol = element_gradients(nodes, tets)
    # the tetrahedra labelled as the lump fill exactly its volume: the mesh conforms to it
    assert vol[mats.labels == 1].sum() == pytest.approx(lump.mesh.volume, rel=1e-9)
    assert vol.sum() == pytest.approx(ball.volume, rel=1e-9)
    assert mats.young_pa[mats.labels == 1] == pytest.approx(10.0 * LIVER.young_pa)
    assert mats.young_pa[mats.labels == 0] == pytest.approx(LIVER.young_pa)
    lam, mu = mats.lame
    assert mu[mats.labels == 1][0] == pytest.approx(10.0 * mu[mats.labels == 0][0])
    twin = _lump((-0.02, 0.0, 0.07), 0.008, LIVER, where="twin")  # a region of the solid's own
    counts = element_materials(nodes, tets, LIVER, [lump, twin]).counts()
    assert set(counts) == {"solid (liver)", "lump (liver*10)", "twin (liver)"}
    assert counts["lump (liver*10)"] == int((mats.labels == 1).sum())
    assert counts["twin (liver)"] > 0 and sum(counts.values()) == len(tets)


def test_assembly_by_groups_is_the_elements_own_sum(ball, cache):
    lump = _lump((0.0, 0.0, 0.06), 0.01)
    nodes, tets = volume_with_inclusions(ball, [lump], cache_dir=cache)
    same = element_materials(nodes, tets, LIVER, [_lump((0.0, 0.0, 0.06), 0.01, LIVER)])
    lam, mu = (float(x[0]) for x in same.lame)
    k_one = stiffness_matrix(nodes, tets, lam, mu)
    assert abs(stiffness_by_groups(nodes, tets, same) - k_one).max() <= 1e-12 * abs(k_one).max()
    np.testing.assert_allclose(
        mass_by_groups(nodes, tets, same), lumped_mass(nodes, tets, LIVER.density_kg_m3)
    )
    # a stiffer lump: K is the soft part's elements plus the lump's, each with its own E
    mats = element_materials(nodes, tets, LIVER, [lump])
    soft, hard = tets[mats.labels == 0], tets[mats.labels == 1]
    lam_h, mu_h = (float(x[mats.labels == 1][0]) for x in mats.lame)
    expect = stiffness_matrix(nodes, soft, lam, mu) + stiffness_matrix(nodes, hard, lam_h, mu_h)
    k = stiffness_by_groups(nodes, tets, mats)
    assert abs(k - expect).max() <= 1e-12 * abs(expect).max()
    assert abs(k - k_one).max() > 0.1 * abs(k_one).max()  # the lump's elements did change


def test_the_solid_with_a_lump_is_stiffer_over_it_as_its_elements_say(ball, cache):
    # the server's FemSolid with per-element materials: K_o over a stiff lump is the one the
    # group-by-group assembly gives, and higher than the same solid's without the lump
    from dataclasses import replace

    from haptic_collab.server.objects.fem import FemParams, FemSolid
    from haptic_collab.server.solid_materials import solid_to_params

    lump = _lump((0.0, 0.0, 0.07), 0.015, subdivisions=1)  # 42 vertices: a small P2 solid
    nodes, tets = volume_with_inclusions(ball, [lump], cache_dir=cache)
    mats = element_materials(nodes, tets, LIVER, [lump])
    params = replace(solid_to_params(LIVER, FemParams()), density_kg_m3=0.0, warp=False)
    plain = FemSolid(ball, params, volume=(nodes, tets))
    lumped = FemSolid(ball, params, volume=(nodes, tets), materials=mats)
    top = int(np.argmax(ball.vertices[:, 2]))
    k_plain, k_lump = plain.contact_stiffness([top])[0], lumped.contact_stiffness([top])[0]
    assert k_lump > (1.0 + STIFFNESS_JND) * k_plain  # a 30 mm lump 15 mm under the pad is felt
    free = np.flatnonzero(np.repeat(~lumped.fixed_nodes, 3))
    k = stiffness_by_groups(lumped.nodes, lumped.elements, mats).tocsc()[free][:, free]
    pt = lumped.patch(top)
    row = np.full(3 * len(lumped.nodes), -1)
    row[free] = np.arange(len(free))
    b = np.zeros(len(free))
    dofs = (3 * pt.indices[:, None] + np.arange(3)).ravel()
    vals = (pt.weights[:, None] * pt.normal[None, :]).ravel()
    ok = row[dofs] >= 0
    np.add.at(b, row[dofs[ok]], vals[ok])
    import scipy.sparse.linalg as spla

    assert 1.0 / float(b @ spla.spsolve(k, b)) == pytest.approx(k_lump, rel=1e-9)


def test_a_lump_is_felt_on_the_linear_elements_with_averaged_nodal_pressure_too(ball, cache):
    # the element of a mesh too large for P2: each node's pressure takes the compliances of its
    # elements in series, so a lump of the solid's own material changes nothing and a stiff one
    # is felt over it
    from dataclasses import replace

    from haptic_collab.server.objects.fem import FemParams, FemSolid
    from haptic_collab.server.solid_materials import solid_to_params

    lump = _lump((0.0, 0.0, 0.07), 0.015, subdivisions=1)
    nodes, tets = volume_with_inclusions(ball, [lump], cache_dir=cache)
    params = replace(
        solid_to_params(LIVER, FemParams()), density_kg_m3=0.0, warp=False, element="anp"
    )
    top = int(np.argmax(ball.vertices[:, 2]))

    def k_top(materials):
        solid = FemSolid(ball, params, volume=(nodes, tets), materials=materials)
        assert solid.element == "anp"
        return float(solid.contact_stiffness([top])[0])

    plain = k_top(None)
    same_material = _lump((0.0, 0.0, 0.07), 0.015, LIVER, subdivisions=1)
    same = k_top(element_materials(nodes, tets, LIVER, [same_material]))
    assert same == pytest.approx(plain, rel=1e-9)
    assert k_top(element_materials(nodes, tets, LIVER, [lump])) > (1.0 + STIFFNESS_JND) * plain


def test_a_large_stiff_lump_is_felt_through_the_liver_and_a_deep_one_is_not(cache):
    """Over a 30 mm lump ten times as stiff as liver, its top 10 mm under the surface, the finger
    pad meets a surface stiffer than beside it (over its twin of liver) by more than a stiffness
    JND; the same lump 30 mm deep is not felt. (A 10 mm lump at 10-20 mm changes K_o by about
    2 % under the 15 mm pad: docs/palpation.md.)"""
    near = measure(0.030, 0.010, subdivisions=3, cache_dir=cache, lump_subdivisions=1)
    assert near.rise > STIFFNESS_JND and near.lump_share > STIFFNESS_JND
    assert abs(near.mesh_asymmetry) < 0.25 * STIFFNESS_JND  # the twin meshes beside alike
    assert near.felt
    deep = measure(0.030, 0.030, subdivisions=3, cache_dir=cache, lump_subdivisions=1)
    assert deep.rise < STIFFNESS_JND and not deep.felt
    assert deep.rise < near.rise


def test_a_lump_that_does_not_fit_is_refused():
    with pytest.raises(ValueError, match="does not fit"):
        sphere_lump(0.05, 0.06)


def test_each_inclusions_surface_is_read_back_from_the_solid_with_its_name_and_ratio(ball, cache):
    """What the viewer is sent (docs/palpation.md): each lump's closed surface at rest, wound
    outward, its file name without folders, its material and its Young's modulus over the
    solid's."""
    lump = _lump((0.02, 0.0, 0.05), 0.01, where="/srv/cases/lump.stl")
    twin = _lump((-0.02, 0.0, 0.05), 0.01, LIVER, where="twin.stl")
    nodes, tets = volume_with_inclusions(ball, [lump, twin], cache_dir=cache)
    mats = element_materials(nodes, tets, LIVER, [lump, twin], young_scale=3.0)
    got = inclusion_surfaces(nodes, tets, mats)
    assert [(s.name, s.material) for s in got] == [("lump.stl", "liver*10"), ("twin.stl", "liver")]
    assert [s.young_ratio for s in got] == pytest.approx([10.0, 1.0])  # the scale cancels
    for s, inc in zip(got, (lump, twin), strict=True):
        mesh = trimesh.Trimesh(s.vertices, s.faces, process=False)
        assert mesh.is_watertight and mesh.is_winding_consistent
        assert mesh.volume == pytest.approx(inc.mesh.volume, rel=1e-9)  # > 0: wound outward
        np.testing.assert_allclose(mesh.bounds, inc.mesh.bounds, atol=1e-12)
    # the whole solid's boundary is its surface; no region, no surface
    v, f = region_boundary(nodes, tets, np.ones(len(tets), dtype=bool))
    assert trimesh.Trimesh(v, f, process=False).volume == pytest.approx(ball.volume, rel=1e-9)
    assert len(f) == len(ball.faces)
    v, f = region_boundary(nodes, tets, np.zeros(len(tets), dtype=bool))
    assert v.shape == (0, 3) and f.shape == (0, 3)
    one = element_materials(nodes, tets, LIVER, [])
    assert inclusion_surfaces(nodes, tets, one) == []


def test_vertex_clustering_keeps_a_surface_under_its_cap_and_its_shape():
    big = trimesh.creation.icosphere(subdivisions=6, radius=0.02)  # 81 920 triangles
    for cap, shape in ((4096, 0.01), (500, 0.1), (60, 0.4)):
        v, f, decimated = cluster_decimate(big.vertices, big.faces, cap)
        assert decimated and 0.2 * cap < len(f) <= cap, (cap, len(f))
        assert f.min() >= 0 and f.max() == len(v) - 1  # every vertex used, none missing
        r = np.linalg.norm(v, axis=1)
        assert np.all(np.abs(r - 0.02) < shape * 0.02), cap  # on the sphere, to a cell
        mesh = trimesh.Trimesh(v, f, process=False)
        # still wound outward, enclosing about the sphere's volume (less the coarser it is)
        assert mesh.volume == pytest.approx(big.volume, rel=shape), cap
    v, f, decimated = cluster_decimate(big.vertices, big.faces, len(big.faces))
    assert not decimated and len(f) == len(big.faces)
    flat = np.zeros((3, 3))  # every corner at one point: nothing left to draw
    v, f, decimated = cluster_decimate(flat, [[0, 1, 2], [0, 2, 1]], 1)
    assert decimated and len(f) == 0


def _server_solid(tmp_path, lump_subdivisions, monkeypatch=None, max_nodes=None):
    """The FEM solid ``haptic server --object fem --subdivisions 2 --inclusion lump.stl`` builds."""
    from haptic_collab.server.main import ServerOptions, build_world

    if max_nodes is not None:
        monkeypatch.setattr("haptic_collab.server.objects.fem.P2_MAX_NODES", max_nodes)
    path = tmp_path / "lump.stl"
    sphere_lump(0.03, 0.01, subdivisions=lump_subdivisions).export(path)
    opts = ServerOptions(
        object="fem",
        subdivisions=2,
        inclusions=(str(path),),
        inclusion_materials=("liver*10",),
        volume_cache=str(tmp_path / "volumes"),
    )
    return build_world(opts).obj


def test_a_solid_with_a_lump_is_quadratic_on_the_sphere_shown_unless_too_large(
    tmp_path, monkeypatch
):
    # near incompressibility linear tetrahedra lock (docs/fem.md): the server builds a solid with
    # a lump with quadratic ones on the parent sphere, showing the sphere asked for
    solid = _server_solid(tmp_path, 1)
    assert solid.element == "p2"
    assert len(solid.rest_vertices) == 162
    assert (solid.materials.labels == 1).sum() > 0  # the lump is in it
    # a lump whose refinement would make the P2 solid too large: linear tetrahedra with averaged
    # nodal pressure (they do not lock either) on the sphere shown, still showing the sphere
    # asked for, never on the parent (a quarter of the vertices)
    small = _server_solid(tmp_path, 1, monkeypatch, max_nodes=len(solid.nodes) - 1)
    assert small.element == "anp"
    assert len(small.rest_vertices) == 162
    assert (small.materials.labels == 1).sum() > 0
