"""``--mesh-repair``: broken CAD-like parts become one closed body, and say what changed.

The parts are built here (a box with a hole, two boxes sharing an edge, overlapping boxes,
duplicated faces and a fin): what a CAD export or a careless merge leaves behind.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from haptic_collab.server.objects.mesh import (
    MeshError,
    load_mesh,
    prepare_mesh,
    repair_report_of,
)
from haptic_collab.server.objects.repair import RepairError, RepairReport, repair_mesh_topology

#: MeshFix (AGPL) is not a dependency: it closes open pieces in a child process when installed.
HAS_MESHFIX = importlib.util.find_spec("pymeshfix") is not None
needs_meshfix = pytest.mark.skipif(not HAS_MESHFIX, reason="pip install pymeshfix (AGPL)")

MESHES = Path(__file__).resolve().parents[1] / "data" / "meshes"
SIDE = 0.1  # [m]


def _box(offset=(0.0, 0.0, 0.0), side: float = SIDE) -> trimesh.Trimesh:
    """A closed box of ``side`` [m] with its lowest corner at ``offset``, 3 mm facets."""
    box = trimesh.creation.box(extents=(side, side, side))
    box.apply_translation(np.asarray(offset) + side / 2)
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=side / 8)
    return trimesh.Trimesh(v, f, process=True)


def box_with_a_hole() -> trimesh.Trimesh:
    """A box with the faces around the middle of its top removed: open, one boundary loop."""
    box = _box()
    centres = box.triangles_center
    top = (centres[:, 2] > SIDE - 1e-9) & (np.linalg.norm(centres[:, :2] - SIDE / 2, axis=1) < 0.02)
    return trimesh.Trimesh(box.vertices, box.faces[~top], process=False)


def two_boxes_sharing_an_edge() -> trimesh.Trimesh:
    """Two boxes touching along one edge (a non-manifold edge once merged), one file."""
    return trimesh.util.concatenate([_box(), _box((SIDE, SIDE, 0.0))])


def overlapping_boxes() -> trimesh.Trimesh:
    """Two boxes overlapping by half (self-intersecting, two bodies): a careless assembly."""
    return trimesh.util.concatenate([_box(), _box((SIDE / 2, 0.0, 0.0))])


def box_with_duplicated_faces_and_a_fin() -> trimesh.Trimesh:
    """A box with 20 faces written twice and a fin: a triangle hanging off one edge."""
    box = _box()
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    edge = box.edges_unique[0]
    tip = v[edge].mean(axis=0) + 0.05 * box.vertex_normals[edge].mean(axis=0)
    fin = np.array([[edge[0], edge[1], len(v)]])
    return trimesh.Trimesh(
        np.vstack([v, tip]), np.vstack([f, f[:20], fin]), process=False, validate=False
    )


def repaired(mesh: trimesh.Trimesh, name: str) -> tuple[trimesh.Trimesh, RepairReport]:
    out = prepare_mesh(mesh, name, repair=True)
    report = repair_report_of(out)
    assert report is not None
    return out, report


BROKEN = {
    "a box with a hole": (box_with_a_hole, SIDE**3, "not closed"),
    "two boxes sharing an edge": (two_boxes_sharing_an_edge, SIDE**3, "not manifold"),
    "overlapping boxes": (overlapping_boxes, 1.5 * SIDE**3, "not manifold"),
    "duplicated faces and a fin": (box_with_duplicated_faces_and_a_fin, SIDE**3, "not closed"),
}


@pytest.mark.parametrize("name", BROKEN)
def test_a_broken_part_is_refused_without_the_flag_and_told_to_try_it(name):
    build, _, words = BROKEN[name]
    with pytest.raises(MeshError, match=words) as err:
        prepare_mesh(build(), name)
    assert "--mesh-repair" in str(err.value)


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=needs_meshfix) if "hole" in n else n for n in BROKEN]
)
def test_the_repair_makes_one_closed_body_of_the_parts_volume(name):
    build, volume, _ = BROKEN[name]
    mesh, report = repaired(build(), name)
    assert mesh.is_watertight and mesh.is_winding_consistent
    edges = np.sort(mesh.edges, axis=1)
    assert np.all(np.unique(edges, axis=0, return_counts=True)[1] == 2)  # manifold
    # one body: the overlapping boxes' union (1.5 boxes); the two boxes on an edge cannot be
    # one 2-manifold, so one of them (either: equal volumes) is kept and the other dropped
    assert mesh.volume == pytest.approx(volume, rel=0.02)
    assert report.changed


def test_the_report_says_what_changed():
    edge = repaired(two_boxes_sharing_an_edge(), "edge")[1]
    assert edge.bodies_joined == 2 and edge.bodies_dropped == 1
    lap = repaired(overlapping_boxes(), "lap")[1]
    assert lap.bodies_joined == 2 and lap.bodies_dropped == 0
    assert lap.volume_change == pytest.approx(-0.25, abs=0.01)  # 2 boxes -> 1.5 boxes
    fin = repaired(box_with_duplicated_faces_and_a_fin(), "fin")[1]
    assert fin.faces_removed == 21  # 20 duplicates and the fin
    line = fin.summary()
    assert "21 faces removed" in line and "0 holes filled" in line and "vertices merged" in line
    assert fin.as_dict()["faces_removed"] == 21


@needs_meshfix
def test_a_hole_is_filled_by_meshfix_in_a_child_process():
    before = set(sys.modules)
    hole = repaired(box_with_a_hole(), "hole")[1]
    assert hole.holes_filled == 1 and hole.bodies_dropped == 0
    assert "pymeshfix" not in set(sys.modules) - before  # AGPL: never imported by the server


def test_a_valid_mesh_is_unchanged_by_the_repair():
    box = _box()
    plain = prepare_mesh(box, "box")
    out, report = repaired(box, "box")
    assert not report.changed
    assert out.volume == pytest.approx(plain.volume, rel=1e-9)
    assert len(out.vertices) == len(plain.vertices)


def test_an_unrepaired_mesh_has_no_report():
    assert repair_report_of(prepare_mesh(_box(), "box")) is None


def test_the_report_survives_refinement():
    out = prepare_mesh(overlapping_boxes(), "lap", repair=True, max_edge_m=0.01)
    report = repair_report_of(out)
    assert report is not None and report.bodies_joined == 2


def test_nothing_closable_is_refused_with_a_reason():
    scrap = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], [[0, 1, 2]], process=False)
    with pytest.raises((RepairError, MeshError)):
        repair_mesh_topology(scrap)


@pytest.mark.skipif(not (MESHES / "ant.ply").is_file(), reason="make meshes: pyvista's ant")
def test_the_ant_of_fifteen_bodies_loads_with_the_flag_keeping_its_largest():
    with pytest.raises(MeshError, match="--mesh-repair"):
        load_mesh(MESHES / "ant.ply", target_size_m=0.2)
    ant = load_mesh(MESHES / "ant.ply", target_size_m=0.2, repair=True)
    report = repair_report_of(ant)
    # 15 bodies united; the legs and antennae that do not touch the body stay apart: the
    # largest body is kept and the report says how many were left out
    assert report is not None and report.bodies_joined == 15
    assert report.bodies_dropped == 8
    assert ant.is_watertight


def test_a_configuration_file_turns_the_repair_on_for_the_server_and_a_room(tmp_path):
    from haptic_collab.server.config import ConfigError, load_server_config

    path = tmp_path / "server.toml"
    path.write_text('mesh_repair = true\n[rooms.lab]\nmesh = "box"\nmesh_repair = false\n')
    config = load_server_config(path)
    assert config["mesh_repair"] is True
    assert config["rooms"] == {"lab": {"mesh": "box", "mesh_repair": False}}
    path.write_text('mesh_repair = "yes"\n')
    with pytest.raises(ConfigError, match="mesh_repair"):
        load_server_config(path)


def test_load_object_mesh_passes_the_flag_to_a_file(tmp_path):
    from haptic_collab.server.objects.shapes import load_object_mesh

    # an STL shares no vertex: its bodies are found by position (boxes off each other's grid)
    path = tmp_path / "lap.stl"
    offset = np.array([0.37, 0.21, 0.13]) * SIDE
    trimesh.util.concatenate([_box(), _box(offset)]).export(path)
    with pytest.raises(MeshError, match="--mesh-repair"):
        load_object_mesh(str(path))
    mesh = load_object_mesh(str(path), repair=True)
    report = repair_report_of(mesh)
    assert report is not None and report.bodies_joined == 2 and report.vertices_merged > 0
    overlap = float(np.prod(SIDE - offset))
    assert mesh.volume == pytest.approx(2 * SIDE**3 - overlap, rel=1e-6)
