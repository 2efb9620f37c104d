"""The stress set: harder closed shapes load by name everywhere a mesh is given."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from haptic_collab.cli import build_parser
from haptic_collab.demo import DemoOptions
from haptic_collab.server.config import load_server_config
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.objects.mesh import MeshError, load_mesh, mesh_warnings, repair_mesh
from haptic_collab.server.objects.shapes import (
    STRESS_MAX_EDGE_M,
    STRESS_MESHES,
    load_object_mesh,
    stress_mesh,
    write_textured_obj,
)
from tests.support.processes import run


@pytest.mark.parametrize("name", STRESS_MESHES)
def test_every_shape_is_one_closed_body_of_hand_size_with_short_edges(name):
    built = stress_mesh(name)
    m = repair_mesh(built, where=name)
    assert len(m.vertices) == len(built.vertices)  # nothing to merge or drop
    assert m.is_watertight and m.is_winding_consistent and m.body_count == 1
    assert m.volume > 0.0 and m.volume == pytest.approx(built.volume)  # already outward
    assert 0.15 <= max(m.extents) <= 0.25
    assert m.edges_unique_length.max() <= STRESS_MAX_EDGE_M
    assert mesh_warnings(m, patch_radius_m=0.015, where=name) == []


@pytest.mark.parametrize("name, euler", [("torus", 0), *((n, 2) for n in STRESS_MESHES[1:])])
def test_the_torus_has_a_hole_and_the_others_none(name, euler):
    assert stress_mesh(name).euler_number == euler  # genus 1 -> 0, a sphere's topology -> 2


def test_the_box_and_the_plate_keep_sharp_edges():
    for name in ("box", "plate"):
        m = stress_mesh(name)
        # every face lies on a side: its normal is along an axis, nothing is rounded off
        assert np.allclose(np.abs(m.face_normals).max(axis=1), 1.0), name
    assert np.allclose(sorted(stress_mesh("box").extents), (0.12, 0.16, 0.20))
    assert 0.008 <= min(stress_mesh("plate").extents) <= 0.010


def test_the_bowl_is_concave_and_its_cavity_empty():
    bowl = stress_mesh("bowl")
    assert bowl.volume < 0.6 * bowl.convex_hull.volume  # the cavity is part of the hull only
    # a hemispherical shell of radii 0.1 and 0.08 m: the cavity holds no material
    assert bowl.volume == pytest.approx(2.0 / 3.0 * np.pi * (0.1**3 - 0.08**3), rel=0.01)


def test_the_noisy_sphere_is_rough_by_about_a_millimetre_and_deterministic():
    a, b = stress_mesh("noisy-sphere"), stress_mesh("noisy-sphere")
    assert np.array_equal(a.vertices, b.vertices)
    dev = np.linalg.norm(a.vertices, axis=1) - 0.075
    assert 0.0003 < dev.std() < 0.0007 and np.abs(dev).max() <= 0.0015 + 1e-12


def test_the_uneven_sphere_is_four_times_finer_on_top():
    m = stress_mesh("uneven")
    z = m.vertices[m.edges_unique][:, :, 2]
    top = np.median(m.edges_unique_length[(z > 0.001).all(axis=1)])
    bottom = np.median(m.edges_unique_length[(z < -0.001).all(axis=1)])
    assert 3.5 < bottom / top < 4.5


def test_shapes_are_fresh_copies_and_unknown_names_are_listed():
    m = stress_mesh("torus")
    m.vertices[0] += 1.0
    assert not np.allclose(stress_mesh("torus").vertices[0], m.vertices[0])
    with pytest.raises(ValueError, match="torus, box, plate, bowl, noisy-sphere, uneven"):
        stress_mesh("sphere")


def test_a_textured_obj_split_at_seams_loads_to_the_seamless_mesh(tmp_path):
    for name in ("torus", "uneven"):  # a cut all round, and poles split once per face
        path = write_textured_obj(tmp_path / f"{name}.obj", name)
        text = path.read_text()
        seamless = stress_mesh(name)
        n_v = sum(1 for line in text.splitlines() if line.startswith("v "))
        n_vt = sum(1 for line in text.splitlines() if line.startswith("vt "))
        assert n_v == n_vt >= len(seamless.vertices) + 30  # split at the seams, as exported
        assert (tmp_path / f"{name}.mtl").is_file()
        m = load_mesh(path)
        assert len(m.vertices) == len(seamless.vertices)
        assert m.is_watertight and m.body_count == 1
        assert m.volume == pytest.approx(seamless.volume, rel=1e-6)
        # the same surface, not only the same counts: each vertex where a seamless one is (to
        # the 9 digits written) and the same faces between them: nothing a contact meets differs
        dist, match = cKDTree(seamless.vertices).query(m.vertices)
        assert dist.max() < 1e-8 and len(set(match.tolist())) == len(match)
        faces = {tuple(sorted(f)) for f in match[np.asarray(m.faces)].tolist()}
        assert faces == {tuple(sorted(f)) for f in np.asarray(seamless.faces).tolist()}


# ------------------------------------------------------------------------ --mesh NAME everywhere
def test_load_object_mesh_takes_names_files_and_the_size_options(tmp_path):
    torus = load_object_mesh("torus")
    assert len(torus.vertices) == len(stress_mesh("torus").vertices)
    small = load_object_mesh("torus", target_size_m=0.1, max_edge_m=0.004)
    assert max(small.extents) == pytest.approx(0.1)
    assert small.edges_unique_length.max() <= 0.004
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=(0.2, 0.2, 0.2)).export(path)
    assert len(load_object_mesh(str(path), max_edge_m=0.01).vertices) > 8
    with pytest.raises(MeshError) as err:
        load_object_mesh("toros")
    msg = str(err.value)
    assert msg.startswith("toros: no such mesh file, and not an object name")
    assert "balloon" in msg and all(n in msg for n in STRESS_MESHES) and "\n" not in msg


@pytest.mark.parametrize("name", ["torus", "bowl", "plate"])
def test_the_server_builds_a_world_on_a_named_shape(name):
    world = build_world(ServerOptions(mesh=name))
    assert world.obj.n_vertices == len(stress_mesh(name).vertices)


def test_mesh_max_edge_refines_the_balloon_and_named_shapes():
    plain = build_world(ServerOptions(mesh="balloon", subdivisions=3))
    fine = build_world(ServerOptions(mesh="balloon", subdivisions=3, mesh_max_edge=0.0075))
    assert fine.obj.n_vertices > 2 * plain.obj.n_vertices
    box = build_world(ServerOptions(mesh="box", mesh_max_edge=0.004))
    assert box.obj.n_vertices > len(stress_mesh("box").vertices)


def test_an_unknown_mesh_name_stops_the_server_with_the_names_listed():
    with pytest.raises(MeshError, match="not an object name"):
        build_world(ServerOptions(mesh="toros"))


def test_mesh_max_edge_is_an_option_of_server_demo_and_configuration_file(tmp_path):
    parse = build_parser().parse_args
    args = parse(["server", "--mesh", "uneven", "--mesh-max-edge", "0.005"])
    assert (args.mesh, args.mesh_max_edge) == ("uneven", 0.005)
    assert parse(["demo", "--mesh", "torus", "--mesh-max-edge", "0.006"]).mesh_max_edge == 0.006
    assert parse(["server"]).mesh_max_edge is None
    config = tmp_path / "server.toml"
    config.write_text('mesh = "bowl"\nmesh_max_edge = 0.005\n')
    # a shape's name is not a path next to the configuration file
    assert load_server_config(config) == {"mesh": "bowl", "mesh_max_edge": 0.005}
    config.write_text('mesh = "bowl.stl"\n')
    assert load_server_config(config)["mesh"] == str(tmp_path / "bowl.stl")


def test_the_demo_passes_the_mesh_options_to_its_server(tmp_path, monkeypatch):
    from haptic_collab import demo

    seen: list[list[str]] = []

    class Started(Exception):
        pass

    def popen(cmd, **kwargs):
        seen.append(list(cmd))
        raise Started

    monkeypatch.setattr(demo.subprocess, "Popen", popen)
    with pytest.raises(Started):
        demo._run_in(tmp_path, 0, DemoOptions(mesh="noisy-sphere", mesh_max_edge=0.005))
    (cmd,) = seen
    server = cmd[cmd.index("server") :]
    assert server[server.index("--mesh") + 1] == "noisy-sphere"
    assert float(server[server.index("--mesh-max-edge") + 1]) == 0.005
    args = build_parser().parse_args(server)
    assert args.mesh_max_edge == 0.005


# ------------------------------------------------------------------- what a user sees at start
def test_haptic_server_refuses_an_unknown_name_and_a_two_body_mesh_in_one_line(tmp_path):
    res = run("server", "--mesh", "toros", "--port", "0", timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    (err,) = [ln for ln in res.stderr.splitlines() if "haptic server: error" in ln]
    assert "toros" in err and "torus, box, plate, bowl, noisy-sphere, uneven" in err
    a = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    b = a.copy()
    b.apply_translation((0.3, 0.0, 0.0))
    path = tmp_path / "pair.stl"
    trimesh.util.concatenate([a, b]).export(path)
    res = run("server", "--mesh", str(path), "--port", "0", timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    (err,) = [ln for ln in res.stderr.splitlines() if "haptic server: error" in ln]
    assert "pair.stl" in err and "2 separate bodies" in err
    assert "--mesh-repair" in err  # the way out it suggests


def test_haptic_server_serves_a_refined_named_shape():
    res = run(
        "server", "--mesh", "plate", "--mesh-max-edge", "0.004", "--port", "0",
        "--duration", "0.5", timeout=120,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    refined = load_object_mesh("plate", max_edge_m=0.004)
    assert f"serving {len(refined.vertices)}-vertex object" in res.stderr
    assert "WARNING" not in res.stderr


def test_the_cli_help_names_every_shape(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["server", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert all(name in text for name in STRESS_MESHES) and "--mesh-max-edge" in text
