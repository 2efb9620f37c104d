"""Gravity for the FEM solid (``haptic server --object fem --gravity``): it sags at start.

What a user would notice: the liver ball stands about 2 cm lower at its top before anyone
touches it, and a column sags as a column of its weight does; the base carries the whole weight,
a heavier lump weighs more; pushes add on top of the sag, a reset returns to the sagged shape
and a checkpoint survives; without gravity the solid is the one it always was; an impossible g
is one clear line at start, and a sag beyond the linear model's reach is a warning naming it.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from pydantic import ValidationError

from haptic_collab.server import snapshots
from haptic_collab.server.config import ConfigError, load_server_config
from haptic_collab.server.main import ServerOptions, build_world, check_templates, room_options
from haptic_collab.server.objects.fem import GRAVITY_MAX_M_S2, FemParams, FemSolid
from haptic_collab.server.objects.fem_elements import (
    element_gravity_loads,
    element_stiffness_matrix,
)
from haptic_collab.server.objects.inclusions import (
    Inclusion,
    element_materials,
    volume_with_inclusions,
)
from haptic_collab.server.objects.mesh import default_balloon, refine_mesh
from haptic_collab.server.solid_materials import SOLID_PRESETS, solid_to_params
from tests.support.skfem_p2p0 import p2p0_stiffness

G = 9.81
LIVER = SOLID_PRESETS["liver"]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("volumes"))


@pytest.fixture(scope="module")
def ball():
    # the default sphere's shape (r 0.1 m), 162 vertices: its P2 solid shows 642
    return default_balloon(subdivisions=2)


@pytest.fixture(scope="module")
def liver():
    """The server's liver preset; a few modes keep the build cheap (the sag is static)."""
    return replace(solid_to_params(LIVER, FemParams()), n_modes=24)


@pytest.fixture(scope="module")
def sagged(ball, liver, cache):
    return FemSolid(ball, replace(liver, gravity_m_s2=G), cache_dir=cache)


@pytest.fixture(scope="module")
def plain(ball, liver, cache):
    return FemSolid(ball, liver, cache_dir=cache)


def _top(solid: FemSolid) -> int:
    return int(np.argmax(solid.mesh_vertices[:, 2]))


def _weight_on_base(solid: FemSolid, lam, mu) -> float:
    """The upward force [N] the fixed base exerts, from the sag and the element's assembly:
    the base's reaction ``K u - F`` summed over the fixed nodes' z rows."""
    nodes, elements = solid.nodes, solid.elements
    k = element_stiffness_matrix(nodes, elements, lam, mu)
    ku = (k @ solid.sag_nodes.ravel()).reshape(-1, 3)
    rho = (
        solid.materials.density_kg_m3 if solid.materials is not None else solid.params.density_kg_m3
    )
    load_z = element_gravity_loads(nodes, elements, rho, G)[:, 2]
    fixed = solid.fixed_nodes
    return float(np.sum(ku[fixed, 2] - load_z[fixed]))


def test_a_column_sags_as_the_analytic_column_under_its_own_weight(cache):
    # nu = 0: a column clamped at its foot is in uniaxial stress rho g (H - z), so
    # u_z(z) = -rho g (H z - z^2 / 2) / E exactly, and nothing moves sideways
    height, e, rho = 0.12, 10.0e3, 1000.0
    column = refine_mesh(trimesh.creation.box(extents=(0.04, 0.04, height)), 0.02)
    params = FemParams(
        young_pa=e, poisson=0.0, density_kg_m3=rho, n_modes=0, base_share=0.0, gravity_m_s2=G
    )
    solid = FemSolid(column, params, cache_dir=cache)
    z = solid.nodes[:, 2] + height / 2.0
    exact = -rho * G * (height * z - z * z / 2.0) / e
    top = -rho * G * height**2 / (2.0 * e)  # 7.1 mm
    assert np.abs(solid.sag_nodes[:, 2] - exact).max() <= 0.005 * abs(top)
    assert np.abs(solid.sag_nodes[:, :2]).max() <= 0.005 * abs(top)
    assert solid.sag_m == pytest.approx(-top, rel=0.005)


def test_the_liver_ball_sags_about_2_cm_as_scikit_fem_solves_it(sagged, cache):
    skfem = pytest.importorskip("skfem")

    top = _top(sagged)
    # the estimate: rho g R^2 / E = 19 mm for the liver ball; the top sinks, not sideways
    assert 0.015 <= -sagged.sag[top, 2] <= 0.025
    assert np.hypot(*sagged.sag[top, :2]) <= 0.05 * -sagged.sag[top, 2]

    # an independent assembly and load: scikit-fem's P2/P0 elasticity and its own body-force form
    # on the same linear mesh, its dofs matched to the solid's nodes by place
    from scipy.spatial import cKDTree

    lam, mu = sagged.params.lame
    rho = sagged.params.density_kg_m3
    basis = skfem.Basis(
        skfem.MeshTet(sagged.linear_nodes.T, sagged.linear_tets.T),
        skfem.ElementVector(skfem.ElementTetP2()),
    )

    @skfem.LinearForm
    def weight(v, w):
        return -rho * G * v[2]

    k = p2p0_stiffness(basis, lam, mu)
    f = skfem.asm(weight, basis)
    dist, node = cKDTree(sagged.nodes).query(basis.doflocs.T)
    assert dist.max() < 1e-12
    z_dof = np.isclose(basis.project(lambda x: np.stack([0 * x[0], 0 * x[0], 1 + 0 * x[0]])), 1)
    fixed = np.flatnonzero(sagged.fixed_nodes[node])
    theirs_flat = skfem.solve(*skfem.condense(k, f, D=fixed))
    theirs = np.zeros_like(sagged.sag_nodes)
    theirs[node[z_dof], 2] = theirs_flat[z_dof]
    assert np.abs(sagged.sag_nodes[:, 2] - theirs[:, 2]).max() <= 1e-6 * np.abs(theirs).max()


def test_the_base_carries_the_whole_weight(sagged):
    weight = LIVER.density_kg_m3 * float(default_balloon(subdivisions=2).volume) * G  # 42 N
    assert _weight_on_base(sagged, *sagged.params.lame) == pytest.approx(weight, rel=1e-6)


def test_a_denser_inclusion_weighs_more_and_the_ball_sags_more(ball, liver, plain, cache):
    lump_mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.03)  # 42 vertices
    lump_mesh.apply_translation((0.0, 0.0, 0.04))
    dense = replace(LIVER, name="dense", density_kg_m3=4.0 * LIVER.density_kg_m3)
    lump = Inclusion(mesh=lump_mesh, material=dense, where="lump")
    nodes, tets = volume_with_inclusions(ball, [lump], cache_dir=cache)
    mats = element_materials(nodes, tets, LIVER, [lump])
    solid = FemSolid(ball, replace(liver, gravity_m_s2=G), volume=(nodes, tets), materials=mats)
    v_all, v_lump = float(ball.volume), float(lump_mesh.volume)
    weight = G * (LIVER.density_kg_m3 * (v_all - v_lump) + dense.density_kg_m3 * v_lump)
    assert _weight_on_base(solid, *mats.lame) == pytest.approx(weight, rel=1e-6)
    same_light = FemSolid(ball, replace(liver, gravity_m_s2=G), volume=(nodes, tets))
    top = _top(solid)
    # the lump adds 3 x its 0.12 kg to the 4.4 kg ball, above the base: the top sinks further
    assert -solid.sag[top, 2] > 1.02 * -same_light.sag[top, 2]


def test_without_gravity_the_solid_is_the_unloaded_one(plain, ball):
    shown = trimesh.Trimesh(plain.mesh_vertices, plain.faces, process=False)
    normals = shown.vertex_normals / np.linalg.norm(shown.vertex_normals, axis=1, keepdims=True)
    assert np.array_equal(plain.rest_vertices[: len(ball.vertices)], ball.vertices)
    assert np.array_equal(plain.rest_vertices, plain.mesh_vertices)
    assert np.array_equal(plain.rest_normals, normals)
    assert not plain.sag.any() and not plain.sag_nodes.any() and plain.sag_m == 0.0
    rest = plain.mesh_vertices
    assert np.array_equal(plain.vertices, rest)
    top = _top(plain)
    plain.step([top], [1.0])
    # the surface is the mesh plus the push's warped response, nothing taken off
    assert np.array_equal(plain.vertices, rest + plain.displacement)
    assert plain.displacement[top, 2] < -1e-3
    plain.reset()
    assert np.array_equal(plain.vertices, rest)
    assert all(not v.any() for v in plain.state().values())  # rest is all zeros, as before


def test_pushes_add_on_top_of_the_sag_and_a_reset_returns_to_it(sagged, plain):
    top = _top(sagged)
    assert np.array_equal(sagged.vertices, sagged.rest_vertices)  # the first tick's surface
    assert np.allclose(sagged.rest_vertices, sagged.mesh_vertices + sagged.sag)
    # K_o, B_o and the coupling are the linear model's, the unloaded mesh's
    keys = [top, sagged.patch_key([0.1, 0.0, 0.0], normal=[1.0, 0.0, 0.0])]
    assert np.allclose(sagged.contact_compliance(keys), plain.contact_compliance(keys), rtol=1e-12)
    assert np.allclose(sagged.contact_damping(keys), plain.contact_damping(keys), rtol=1e-12)
    for _ in range(5):
        sagged.step(keys, [2.0, 1.0])
        plain.step(keys, [2.0, 1.0])
    # the linear model: the same response to the same pushes, from the sagged rest
    lin_g, lin_0 = sagged.linear_displacement, plain.linear_displacement
    assert np.abs(lin_g - lin_0).max() <= 1e-12 * np.abs(lin_0).max()
    dent = -sagged.displacement[top, 2]
    assert dent == pytest.approx(-plain.displacement[top, 2], rel=0.05)  # warped about the sag
    assert dent > 0.005  # 2 N on the liver top: about 1 cm more
    assert sagged.max_displacement_m < 0.5 * (sagged.max_displacement_m + sagged.sag_m)
    sagged.reset()
    plain.reset()
    assert np.array_equal(sagged.vertices, sagged.rest_vertices)
    assert sagged.vertices[top, 2] < sagged.mesh_vertices[top, 2] - 0.015  # still sagged
    assert sagged.max_displacement_m == 0.0
    rest = sagged.state()
    assert not rest["modal_x"].any() and not rest["modal_v"].any()
    assert np.array_equal(rest["u"].reshape(-1, 3)[top], sagged.sag_nodes[top])


def test_a_checkpoint_of_a_sagged_solid_resumes_where_it_was(sagged, plain, ball, liver, cache):
    top = _top(sagged)
    for _ in range(3):
        sagged.step([top], [1.5])
    shown = sagged.vertices
    again = FemSolid(ball, replace(liver, gravity_m_s2=G), cache_dir=cache)
    # a drain's snapshot names the object: a sagged solid's is not resumed without gravity
    assert snapshots.describe(again) == snapshots.describe(sagged)
    assert snapshots.describe(plain)["params_sha256"] != snapshots.describe(sagged)["params_sha256"]
    snapshots.set_object_state(again, snapshots.object_state(sagged))
    assert np.array_equal(again.vertices, shown)
    sagged.step([top], [1.5])
    again.step([top], [1.5])
    assert np.allclose(again.vertices, sagged.vertices, rtol=0.0, atol=1e-12)
    sagged.reset()


@pytest.mark.parametrize("g", [-1.0, float("nan"), float("inf"), GRAVITY_MAX_M_S2 + 1.0])
def test_an_impossible_gravity_is_refused_by_name(g):
    with pytest.raises(ValidationError, match="gravity_m_s2"):
        FemParams(gravity_m_s2=g)
    with pytest.raises(ValueError, match=r"--gravity must be in \[0, 100\] m/s\^2"):
        build_world(ServerOptions(object="fem", gravity_m_s2=g, subdivisions=1))


def test_gravity_on_the_balloon_is_refused():
    with pytest.raises(ValueError, match="--gravity needs --object fem"):
        build_world(ServerOptions(gravity_m_s2=G, subdivisions=1))


def test_the_config_file_and_the_command_line_take_gravity(tmp_path):
    good = tmp_path / "g.toml"
    good.write_text('object = "fem"\ngravity = 9.81\n[rooms.heavy]\ngravity = 20\n')
    assert load_server_config(good)["gravity"] == 9.81
    assert load_server_config(good)["rooms"] == {"heavy": {"gravity": 20.0}}
    opts = ServerOptions(object="fem", gravity_m_s2=9.81)
    assert room_options(opts, {"gravity": 20.0}).gravity_m_s2 == 20.0
    assert room_options(opts, {"object": "balloon"}).gravity_m_s2 == 9.81
    # a template of the balloon under a server-wide gravity fails the start, not the first join
    with pytest.raises(ValueError, match=r"\[room_templates.toy\]: --gravity needs --object fem"):
        check_templates(replace(opts, room_templates={"toy": {"object": "balloon"}}))
    bad = tmp_path / "bad.toml"
    bad.write_text("gravity = 981\n")
    with pytest.raises(ConfigError, match=r"gravity must be in \[0, 100\] m/s\^2"):
        load_server_config(bad)


def test_the_command_line_takes_gravity_9_81_without_a_value_and_refuses_a_bad_one(capsys):
    from haptic_collab.cli import build_parser, run

    assert run.GRAVITY_MAX_M_S2 == GRAVITY_MAX_M_S2
    parser = build_parser()
    assert run._server_options(parser.parse_args(["server"])).gravity_m_s2 == 0.0
    given = parser.parse_args(["server", "--gravity", "--object", "fem"])
    assert run._server_options(given).gravity_m_s2 == 9.81
    given = parser.parse_args(["server", "--object", "fem", "--gravity", "3.7"])
    assert run._server_options(given).gravity_m_s2 == 3.7
    for bad, words in (("-3", "must be >= 0"), ("nan", "must be finite"), ("981", "at most 100")):
        with pytest.raises(SystemExit):
            parser.parse_args(["server", "--object", "fem", "--gravity", bad])
        assert words in capsys.readouterr().err


def test_a_sag_beyond_the_linear_model_is_a_warning_naming_it(cache, caplog):
    column = refine_mesh(trimesh.creation.box(extents=(0.04, 0.04, 0.12)), 0.02)
    params = FemParams(young_pa=3.5e3, poisson=0.0, density_kg_m3=1000.0, n_modes=0, base_share=0.0)
    with caplog.at_level(logging.WARNING, logger="haptic.server.fem"):
        FemSolid(column, replace(params, gravity_m_s2=G * 0.85), cache_dir=cache)
        assert not caplog.records  # 17.2 mm, 14 % of its height: under the bound
        FemSolid(column, replace(params, gravity_m_s2=G), cache_dir=cache)
    (record,) = caplog.records  # rho g H^2 / (2 E) = 20.2 mm, 17 % of 120 mm
    assert "20.2 mm" in record.getMessage() and "17 %" in record.getMessage()


def test_a_user_touches_the_sagged_surface_from_the_first_tick(sagged, plain):
    from haptic_collab.server.world import ContactInput, World

    top = _top(sagged)
    sag = -sagged.sag[top, 2]  # about 20 mm
    above = np.array([0.0, 0.0, 0.1 - sag / 2.0])  # inside the mesh, above the sagged top
    into = np.array([0.0, 0.0, 0.1 - sag - 0.003])  # 3 mm into the sagged top
    for solid, probe, depth in ((plain, above, sag / 2.0), (sagged, above, -sag / 2.0),
                                (sagged, into, 0.003)):  # fmt: skip
        solid.reset()
        out = World(solid).tick({"A": ContactInput(probe=probe, force=np.zeros(3))})["A"]
        assert out.penetration_m == pytest.approx(depth, abs=0.0005)
        if solid is sagged:  # the lone user's rest plane is on the sagged surface
            assert out.rest_plane is not None
            assert out.rest_plane.penetration(*probe) == pytest.approx(depth, abs=0.0005)
        solid.reset()
