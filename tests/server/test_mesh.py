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
    refine_mesh,
    repair_mesh,
    scale_mesh_to_size,
)

#: Real meshes fetched from published packages by ``make meshes`` (tools/fetch_meshes.py).
REAL = Path(__file__).resolve().parents[1] / "data" / "meshes"


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


def test_a_scene_of_one_body_in_two_parts_is_flattened_into_one_closed_mesh(tmp_path):
    cube = unit_cube()  # one body stored as two geometries (two materials, say)
    top = trimesh.Trimesh(cube.vertices, cube.faces[:6], process=False)
    bottom = trimesh.Trimesh(cube.vertices, cube.faces[6:], process=False)
    path = tmp_path / "parts.glb"
    trimesh.Scene([top, bottom]).export(path)
    m = load_mesh(path)
    assert m.is_watertight and len(m.vertices) == 8
    assert m.volume == pytest.approx(1.0)


# ------------------------------------------------------------------------------ sanity warnings
def test_the_default_balloon_draws_no_warning():
    assert mesh_warnings(default_balloon(), patch_radius_m=0.015) == []


def test_a_sphere_exported_in_millimetres_is_refused_and_the_scale_suggested(tmp_path):
    path = tmp_path / "ball_mm.stl"
    default_balloon(radius_m=100.0).export(path)  # a 0.1 m balloon written in millimetres
    with pytest.raises(MeshError) as err:
        load_mesh(path)  # 200 "m" across: a unit mistake, refused before the server starts
    msg = str(err.value)
    assert "ball_mm.stl" in msg and "200 m across" in msg and "outside 1 mm - 20 m" in msg
    assert "--mesh-scale 0.001" in msg and "--mesh-size" in msg
    assert mesh_warnings(load_mesh(path, scale=0.001)) == []
    assert mesh_warnings(load_mesh(path, target_size_m=0.2)) == []
    # the warning itself still explains a mesh in memory
    warnings = mesh_warnings(default_balloon(radius_m=100.0), where="ball_mm.stl")
    assert len(warnings) == 1 and "--mesh-scale 0.001" in warnings[0], warnings


def test_a_five_metre_object_loads_with_a_warning(tmp_path):
    path = tmp_path / "ball_cm.stl"
    default_balloon(radius_m=2.5).export(path)  # a 5 cm ball written in centimetres
    mesh = load_mesh(path)
    warnings = mesh_warnings(mesh, where=str(path))
    assert len(warnings) == 1 and "5 m across" in warnings[0], warnings
    assert "centimetres" in warnings[0] and "--mesh-scale 0.01" in warnings[0]


def test_a_tiny_object_warns_and_suggests_mesh_size():
    warnings = mesh_warnings(default_balloon(radius_m=0.002))
    assert any("outside 1 cm - 2 m" in w and "--mesh-size" in w for w in warnings), warnings


def test_an_eight_vertex_box_warns_that_it_cannot_dent():
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    warnings = mesh_warnings(box, where="box.stl")
    assert len(warnings) == 1, warnings
    assert "box.stl: only 8 vertices" in warnings[0]


def test_a_mesh_too_coarse_for_the_finger_pad_warns_and_the_suggested_refinement_cures_it():
    coarse = default_balloon(subdivisions=3)  # 642 vertices, 15 mm edges
    warnings = mesh_warnings(coarse, patch_radius_m=0.015)
    assert len(warnings) == 1 and "too coarse for a finger pad" in warnings[0], warnings
    assert "--mesh-max-edge 0.0075" in warnings[0]
    # the same mesh is fine for a finger pad twice as wide
    assert mesh_warnings(coarse, patch_radius_m=0.03) == []
    # and doing what the message says silences it
    refined = refine_mesh(coarse, 0.0075)
    assert mesh_warnings(refined, patch_radius_m=0.015) == []
    assert refined.is_watertight and refined.volume == pytest.approx(coarse.volume)


def test_scale_mesh_to_size_sets_the_largest_extent_and_keeps_proportions():
    box = trimesh.creation.box(extents=(100.0, 50.0, 20.0))
    scaled = scale_mesh_to_size(box.vertices, 0.2)
    assert mesh_size_m(scaled) == pytest.approx(0.2)
    assert np.allclose(np.ptp(scaled, axis=0), [0.2, 0.1, 0.04])
    assert np.allclose(box.vertices, trimesh.creation.box(extents=(100.0, 50.0, 20.0)).vertices)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="size_m"):
            scale_mesh_to_size(box.vertices, bad)


# --------------------------------------------------------------------------- refused before start
def two_cubes(offset: tuple[float, float, float]) -> trimesh.Trimesh:
    """Two 0.1 m cubes, the second moved by ``offset`` [m]."""
    a = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    b = a.copy()
    b.apply_translation(offset)
    both = trimesh.util.concatenate([a, b])
    assert isinstance(both, trimesh.Trimesh)
    return both


def test_two_disjoint_cubes_are_refused_as_several_bodies(tmp_path):
    m = two_cubes((0.3, 0.0, 0.0))
    path = write_obj(tmp_path / "two.obj", m.vertices, m.faces)
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    msg = str(err.value)
    assert "two.obj" in msg and "2 separate bodies" in msg and "keep the largest" in msg
    assert "\n" not in msg


def test_a_scene_of_two_separate_objects_is_refused_as_several_bodies(tmp_path):
    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(1, 1, 1))
    b.apply_translation((3.0, 0.0, 0.0))
    path = tmp_path / "two.glb"
    trimesh.Scene([a, b]).export(path)
    with pytest.raises(MeshError, match="2 separate bodies"):
        load_mesh(path)


def test_a_book_of_three_closed_pages_on_one_spine_is_refused_as_non_manifold(tmp_path):
    # three thin tetrahedra share the spine A-B: that edge belongs to six faces
    spine = [(0.0, 0.0, 0.0), (0.0, 0.0, 0.1)]
    verts, faces = list(spine), []
    for k in range(3):
        t = 2.0 * np.pi * k / 3.0
        c, s = np.cos(t), np.sin(t)
        verts += [(0.1 * c, 0.1 * s, 0.03), (0.1 * c - 0.02 * s, 0.1 * s + 0.02 * c, 0.07)]
        p, q = len(verts) - 2, len(verts) - 1
        faces += [(0, 1, p), (0, q, 1), (0, p, q), (1, q, p)]
    path = write_obj(tmp_path / "book.obj", np.array(verts), np.array(faces))
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    msg = str(err.value)
    assert "book.obj" in msg and "not manifold" in msg
    assert "1 edge shared by more than two faces" in msg


def test_two_cubes_touching_at_a_corner_are_refused_as_non_manifold(tmp_path):
    m = two_cubes((0.1, 0.1, 0.1))  # closed, every edge has two faces, one shared vertex
    path = write_obj(tmp_path / "corner.obj", m.vertices, m.faces)
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    msg = str(err.value)
    assert "corner.obj" in msg and "not manifold" in msg and "at 1 vertex" in msg


@pytest.mark.parametrize("radius_m, where", [(0.00025, "0.0005 m across"), (25.0, "50 m across")])
def test_an_absurdly_small_or_large_object_is_refused(tmp_path, radius_m, where):
    path = tmp_path / "ball.stl"
    default_balloon(radius_m=radius_m, subdivisions=2).export(path)
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    msg = str(err.value)
    assert "ball.stl" in msg and where in msg and "outside 1 mm - 20 m" in msg
    assert "--mesh-size" in msg


def test_the_size_is_checked_after_scaling(tmp_path):
    path = tmp_path / "ball.stl"
    default_balloon(radius_m=0.1, subdivisions=2).export(path)
    with pytest.raises(MeshError, match="200 m across after scaling"):
        load_mesh(path, scale=1000.0)
    assert mesh_size_m(load_mesh(path, target_size_m=15.0).vertices) == pytest.approx(15.0)


def sliver_at(mesh: trimesh.Trimesh, n_edges: int) -> trimesh.Trimesh:
    """``mesh`` with a T-junction on each of ``n_edges`` edges, closed by a zero-area sliver.

    On each edge (a, b) one side face (a, b, c) is split at the edge's midpoint m and the
    other side is left whole; the crack a-m-b is filled with the collinear face (a, b, m). The
    result is watertight, but only through the slivers.
    """
    verts = [tuple(v) for v in mesh.vertices]
    faces = [tuple(int(i) for i in f) for f in mesh.faces]
    used: set[int] = set()
    done = 0
    for fi, (a, b, c) in enumerate(list(faces)):
        if done == n_edges:
            break
        others = [
            fj for fj, g in enumerate(faces) if fj != fi and a in g and b in g and fj not in used
        ]
        if fi in used or not others:
            continue
        used.update((fi, others[0]))
        verts.append(tuple((np.asarray(verts[a]) + np.asarray(verts[b])) / 2.0))
        m = len(verts) - 1
        faces[fi] = (a, m, c)
        faces += [(m, b, c), (a, b, m)]
        done += 1
    assert done == n_edges
    return trimesh.Trimesh(np.array(verts), np.array(faces), process=False)


def test_a_few_collapsed_faces_are_dropped_silently():
    ball = default_balloon(0.1, 3)  # 1280 faces
    a, b = ball.faces[0][:2]
    extra = np.vstack([ball.faces, [[a, a, b], [b, b, a]]])  # zero area, no hole behind them
    m = repair_mesh(trimesh.Trimesh(ball.vertices, extra, process=False))
    assert m.is_watertight and len(m.faces) == len(ball.faces)
    assert m.volume == pytest.approx(ball.volume)


def test_a_mesh_closed_only_through_a_degenerate_sliver_is_refused():
    cracked = sliver_at(default_balloon(0.1, 3), 1)
    assert cracked.is_watertight  # closed as stored
    with pytest.raises(MeshError) as err:
        repair_mesh(cracked, where="cracked.stl")
    msg = str(err.value)
    assert "cracked.stl" in msg and "closed only through 1 degenerate" in msg
    assert "T-junction" in msg


def test_a_mesh_with_many_degenerate_faces_is_refused():
    broken = sliver_at(default_balloon(0.1, 2), 10)  # 10 slivers in 340 faces: 2.9 %
    with pytest.raises(MeshError) as err:
        repair_mesh(broken, where="broken.obj")
    msg = str(err.value)
    assert "broken.obj: 10 of 340 faces (2.9 %) are degenerate" in msg
    assert "more than the 1 %" in msg


# ------------------------------------------------------------------------------------ refinement
def test_a_coarse_box_is_refined_to_the_edge_bound_and_keeps_its_sharp_edges(tmp_path):
    path = tmp_path / "box_mm.stl"
    trimesh.creation.box(extents=(200.0, 150.0, 100.0)).export(path)  # 12 faces, millimetres
    box = load_mesh(path, scale=0.001, max_edge_m=0.007)
    assert len(box.vertices) > 1000 and box.edges_unique_length.max() <= 0.007
    assert box.is_watertight and box.volume == pytest.approx(0.2 * 0.15 * 0.1)
    # no smoothing: every face still lies on a side of the box, its normal along an axis
    assert np.allclose(np.abs(box.face_normals).max(axis=1), 1.0)
    assert np.allclose(box.extents, (0.2, 0.15, 0.1))
    assert mesh_warnings(box) == []
    # the bound is in metres, after --mesh-size
    sized = load_mesh(path, target_size_m=0.4, max_edge_m=0.007)
    assert sized.edges_unique_length.max() <= 0.007 and len(sized.vertices) > len(box.vertices)


def test_refinement_of_a_fine_mesh_changes_nothing():
    ball = default_balloon(0.1, 4)  # edges below 8.5 mm
    assert len(refine_mesh(ball, 0.01).vertices) == len(ball.vertices)


def test_a_refinement_too_fine_is_refused_before_any_work():
    with pytest.raises(MeshError) as err:
        refine_mesh(trimesh.creation.box(extents=(0.2, 0.2, 0.2)), 0.0001, where="box.stl")
    msg = str(err.value)
    assert "box.stl" in msg and "0.1 mm" in msg and "--mesh-max-edge" in msg
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="max_edge_m"):
            refine_mesh(default_balloon(), bad)


# ------------------------------------------------------------------- real meshes from packages
def real(name: str) -> Path:
    """A fetched mesh file; the test is skipped when it is not there."""
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is missing: run `make meshes` (python tools/fetch_meshes.py)")
    path = REAL / name
    if not path.is_file():
        pytest.skip(f"{path} is missing: run `make meshes` (python tools/fetch_meshes.py)")
    return path


def test_the_stanford_bunny_loads_closed_at_hand_size():
    bunny = load_mesh(real("bunny.obj"), target_size_m=0.2)
    assert len(bunny.vertices) == 1839 and bunny.body_count == 1
    assert bunny.is_watertight and bunny.volume > 0.0
    assert mesh_size_m(bunny.vertices) == pytest.approx(0.2)


def test_the_cad_nut_loads_and_refines_to_the_finger_pad_with_its_hole_and_edges():
    plain = load_mesh(real("nut.ply"), target_size_m=0.2)
    assert len(plain.vertices) == 523 and plain.euler_number == 0  # genus 1: the threaded hole
    assert any("too coarse" in w for w in mesh_warnings(plain)), mesh_warnings(plain)
    nut = load_mesh(real("nut.ply"), target_size_m=0.2, max_edge_m=0.007)
    assert nut.edges_unique_length.max() <= 0.007 and len(nut.vertices) > 4 * 523
    assert nut.is_watertight and nut.body_count == 1 and nut.euler_number == 0
    assert nut.volume == pytest.approx(plain.volume, rel=1e-9)  # the shape is unchanged
    assert mesh_warnings(nut) == []


def test_the_ant_of_fifteen_bodies_is_refused():
    with pytest.raises(MeshError) as err:
        load_mesh(real("ant.ply"))
    msg = str(err.value)
    assert "ant.ply" in msg and "15 separate bodies" in msg and "keep the largest" in msg


def test_the_open_bunny_scan_is_refused_as_not_closed():
    with pytest.raises(MeshError) as err:
        load_mesh(real("StanfordBunny.ply"))
    msg = str(err.value)
    assert "StanfordBunny.ply" in msg and "not closed" in msg and "watertight" in msg
