"""Mesh loading: closed meshes load (repaired and scaled), broken ones are refused clearly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from haptic_collab.server.objects.mesh import (
    MeshError,
    default_balloon,
    load_mesh,
    mesh_size_m,
    mesh_warnings,
    scale_mesh_to_size,
)


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, extra: str = "") -> Path:
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    lines += [extra] if extra else []
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def unit_cube() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 1.0, 1.0))


@pytest.mark.parametrize("subdivisions, count", [(0, 12), (3, 642), (4, 2562)])
def test_default_balloon_is_a_closed_sphere_of_the_requested_size(subdivisions, count):
    m = default_balloon(radius_m=0.1, subdivisions=subdivisions)
    assert len(m.vertices) == count
    assert m.is_watertight and m.volume > 0
    assert np.allclose(np.linalg.norm(m.vertices, axis=1), 0.1)


@pytest.mark.parametrize(
    "kwargs", [{"radius_m": 0.0}, {"radius_m": float("nan")}, {"subdivisions": 9}]
)
def test_default_balloon_refuses_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        default_balloon(**kwargs)


def test_open_box_is_refused_as_not_closed(tmp_path):
    cube = unit_cube()
    path = write_obj(tmp_path / "open_box.obj", cube.vertices, cube.faces[:-2])  # lid removed
    with pytest.raises(MeshError, match="not closed") as err:
        load_mesh(path)
    assert "open_box.obj" in str(err.value) and "watertight" in str(err.value)


def test_garbage_stl_is_refused_as_unparsable(tmp_path):
    path = tmp_path / "garbage.stl"
    path.write_bytes(bytes(range(256)) * 3)
    with pytest.raises(MeshError, match="could not parse"):
        load_mesh(path)


def test_missing_file_and_unknown_format_are_refused(tmp_path):
    with pytest.raises(MeshError, match="does not exist"):
        load_mesh(tmp_path / "nope.stl")
    other = tmp_path / "mesh.xyz"
    other.write_text("0 0 0\n")
    with pytest.raises(MeshError, match="unsupported mesh format"):
        load_mesh(other)


def test_file_without_faces_is_refused(tmp_path):
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError, match="no triangle mesh|no faces"):
        load_mesh(path)


def test_seam_split_obj_merges_to_a_closed_cube(tmp_path):
    cube = unit_cube()
    # every face gets its own three vertices and texture coordinates, as exporters do at seams
    verts = cube.vertices[cube.faces].reshape(-1, 3)
    lines = [f"v {x} {y} {z}" for x, y, z in verts]
    lines += ["vt 0 0\nvt 1 0\nvt 0 1"] * len(cube.faces)
    lines += [
        f"f {3 * i + 1}/{3 * i + 1} {3 * i + 2}/{3 * i + 2} {3 * i + 3}/{3 * i + 3}"
        for i in range(len(cube.faces))
    ]
    path = tmp_path / "seams.obj"
    path.write_text("\n".join(lines) + "\n")
    m = load_mesh(path)
    assert m.is_watertight
    assert len(m.vertices) == 8
    assert m.volume == pytest.approx(1.0)


def test_millimetre_cube_is_scaled_to_metres(tmp_path):
    path = tmp_path / "cube_mm.stl"
    trimesh.creation.box(extents=(100.0, 50.0, 20.0)).export(path)
    by_scale = load_mesh(path, scale=0.001)
    assert np.allclose(sorted(by_scale.extents), [0.02, 0.05, 0.1])
    by_size = load_mesh(path, target_size_m=0.2)
    assert max(by_size.extents) == pytest.approx(0.2)
    assert by_size.volume == pytest.approx(0.2 * 0.1 * 0.04)
    with pytest.raises(ValueError, match="either scale or target_size_m"):
        load_mesh(path, scale=0.001, target_size_m=0.2)
    with pytest.raises(ValueError, match="scale"):
        load_mesh(path, scale=-1.0)


def test_inside_out_mesh_is_turned_outward(tmp_path):
    cube = unit_cube()
    path = write_obj(tmp_path / "inverted.obj", cube.vertices, cube.faces[:, ::-1])
    m = load_mesh(path)
    assert m.volume == pytest.approx(1.0)
    # outward normals: the face normal on the +x side points to +x
    centers = m.triangles_center
    side = centers[:, 0] > 0.49
    assert np.all(m.face_normals[side, 0] > 0.99)


def test_flat_closed_mesh_is_refused_as_degenerate(tmp_path):
    # a "tetrahedron" whose four vertices are coplanar: watertight but encloses no volume
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    path = write_obj(tmp_path / "flat.obj", verts, faces)
    with pytest.raises(MeshError, match="encloses zero volume"):
        load_mesh(path)


def test_non_finite_coordinates_are_refused(tmp_path):
    cube = unit_cube()
    verts = cube.vertices.copy()
    verts[0, 0] = np.nan
    path = write_obj(tmp_path / "nan.obj", verts, cube.faces)
    with pytest.raises(MeshError, match="NaN"):
        load_mesh(path)


@pytest.mark.parametrize("suffix", ["glb", "ply", "off", "stl"])
def test_balloon_round_trips_through_each_format(tmp_path, suffix):
    src = default_balloon(0.1, 2)
    path = tmp_path / f"ball.{suffix}"
    src.export(path)
    m = load_mesh(path)
    assert len(m.vertices) == len(src.vertices)
    assert m.volume == pytest.approx(src.volume, rel=1e-6)


def test_scene_with_two_bodies_is_flattened_into_one_mesh(tmp_path):
    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(1, 1, 1))
    b.apply_translation((3.0, 0.0, 0.0))
    path = tmp_path / "two.glb"
    trimesh.Scene([a, b]).export(path)
    m = load_mesh(path)
    assert m.is_watertight
    assert m.volume == pytest.approx(2.0)
    assert m.extents[0] == pytest.approx(4.0)


# ------------------------------------------------------------------------------ sanity warnings
def test_the_default_balloon_draws_no_warning():
    assert mesh_warnings(default_balloon(), patch_radius_m=0.015) == []


def test_a_sphere_exported_in_millimetres_warns_and_suggests_the_scale(tmp_path):
    path = tmp_path / "ball_mm.stl"
    default_balloon(radius_m=100.0).export(path)  # a 0.1 m balloon written in millimetres
    mesh = load_mesh(path)
    warnings = mesh_warnings(mesh, where=str(path))
    assert len(warnings) == 1, warnings
    assert "ball_mm.stl" in warnings[0] and "200 m across" in warnings[0]
    assert "--mesh-scale 0.001" in warnings[0] and "--mesh-size" in warnings[0]
    assert mesh_warnings(load_mesh(path, scale=0.001)) == []
    assert mesh_warnings(load_mesh(path, target_size_m=0.2)) == []


def test_a_tiny_object_warns_and_suggests_mesh_size():
    warnings = mesh_warnings(default_balloon(radius_m=0.002))
    assert any("outside 1 cm - 2 m" in w and "--mesh-size" in w for w in warnings), warnings


def test_an_eight_vertex_box_warns_that_it_cannot_dent():
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    warnings = mesh_warnings(box, where="box.stl")
    assert len(warnings) == 1, warnings
    assert "box.stl: only 8 vertices" in warnings[0]


def test_a_mesh_too_coarse_for_the_finger_pad_warns():
    coarse = default_balloon(subdivisions=3)  # 642 vertices, 15 mm edges
    warnings = mesh_warnings(coarse, patch_radius_m=0.015)
    assert len(warnings) == 1 and "too coarse for a finger pad" in warnings[0], warnings
    # the same mesh is fine for a finger pad twice as wide
    assert mesh_warnings(coarse, patch_radius_m=0.03) == []


def test_scale_mesh_to_size_sets_the_largest_extent_and_keeps_proportions():
    box = trimesh.creation.box(extents=(100.0, 50.0, 20.0))
    scaled = scale_mesh_to_size(box.vertices, 0.2)
    assert mesh_size_m(scaled) == pytest.approx(0.2)
    assert np.allclose(np.ptp(scaled, axis=0), [0.2, 0.1, 0.04])
    assert np.allclose(box.vertices, trimesh.creation.box(extents=(100.0, 50.0, 20.0)).vertices)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="size_m"):
            scale_mesh_to_size(box.vertices, bad)
