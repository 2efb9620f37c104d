"""The hand-written closest-point geometry of server.contacts against trimesh as the reference.

The vectorized point-triangle routine is kept over ``trimesh.triangles.closest_point`` for speed
(it also yields the barycentric coordinates the normal is interpolated with); these tests pin it
to trimesh's results.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from haptic_collab.server.contacts import (
    SurfaceIndex,
    _closest_on_triangle,
    _closest_on_triangles,
    closest_point,
)
from haptic_collab.server.objects.balloon import Balloon

R = 0.1


def trimesh_closest(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """trimesh's closest points (k, 3) [m] on triangles (k, 3, 3) to the point p (3,)."""
    return trimesh.triangles.closest_point(tri, np.repeat(p[None, :], len(tri), axis=0))


def test_closest_points_and_barycentrics_on_triangles_match_trimesh():
    rng = np.random.default_rng(7)
    k = 3000
    # centimetre triangles around a probe at the origin, as on the product's meshes
    tri = rng.normal(size=(k, 3, 3)) * 0.01 + rng.normal(size=(k, 1, 3)) * 0.01
    p = np.zeros(3)
    points, bary = _closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
    assert points.shape == (k, 3) and bary.shape == (k, 3)
    assert np.abs(points - trimesh_closest(p, tri)).max() < 1e-12
    # barycentrics: a convex combination of the vertices that is the point itself
    assert np.all(bary >= 0.0) and np.all(bary <= 1.0)
    assert np.abs(bary.sum(axis=1) - 1.0).max() < 1e-12
    assert np.abs(np.einsum("ki,kij->kj", bary, tri) - points).max() < 1e-12
    # every region of a triangle was exercised: face interior, edges, vertices
    regions = np.count_nonzero(bary > 0.0, axis=1)
    assert {1, 2, 3} <= set(regions.tolist())


@pytest.mark.parametrize("collapsed", [(0, 1), (1, 2), (2, 0), (0, 1, 2)])
def test_triangles_with_coincident_vertices_match_trimesh(collapsed):
    rng = np.random.default_rng(len(collapsed) * 10 + collapsed[0])
    tri = rng.normal(size=(500, 3, 3)) * 0.01
    for j in collapsed[1:]:
        tri[:, j] = tri[:, collapsed[0]]
    p = rng.normal(size=3) * 0.01
    points, bary = _closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
    assert np.abs(points - trimesh_closest(p, tri)).max() < 1e-12
    assert np.abs(np.einsum("ki,kij->kj", bary, tri) - points).max() < 1e-12


def test_a_face_squashed_flat_gives_its_nearest_edge_point_not_a_point_centimetres_away():
    """Three vertices in a line (a face flattened by the deformation): nearest on the segment."""
    rng = np.random.default_rng(11)
    a = rng.normal(size=(400, 3)) * 0.01
    b = rng.normal(size=(400, 3)) * 0.01
    c = a + rng.uniform(0.05, 0.95, size=(400, 1)) * (b - a)  # c on the segment ab
    p = rng.normal(size=3) * 0.01
    with np.errstate(all="raise"):  # no "invalid value" on the way
        points, bary = _closest_on_triangles(p, a, b, c)
    # the truth: the nearest point of the segment ab
    t = np.clip(((p - a) * (b - a)).sum(axis=1) / ((b - a) ** 2).sum(axis=1), 0.0, 1.0)
    truth = a + t[:, None] * (b - a)
    assert np.abs(points - truth).max() < 1e-12
    assert np.abs(points - trimesh_closest(p, np.stack([a, b, c], axis=1))).max() < 1e-12
    assert (
        np.abs(bary[:, 0, None] * a + bary[:, 1, None] * b + bary[:, 2, None] * c - points).max()
        < 1e-12
    )


def test_the_one_triangle_routine_gives_the_same_numbers_as_the_batch():
    """track_proxy's plain-float routine against the vectorized one (and trimesh): the same
    points, barycentrics and distances to the last bit, on ordinary, degenerate and squashed
    triangles, with the probe off every region of them."""
    rng = np.random.default_rng(5)
    tri = rng.normal(size=(1200, 3, 3)) * 0.01 + rng.normal(size=(1200, 1, 3)) * 0.01
    tri[100:200, 1] = tri[100:200, 0]  # two corners coincide
    tri[200:300, 1:] = tri[200:300, :1]  # a point
    tri[300:400, 2] = tri[300:400, 0] + 0.3 * (tri[300:400, 1] - tri[300:400, 0])  # a segment
    for p in (np.zeros(3), rng.normal(size=3) * 0.01):
        points, bary = _closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
        gaps = points - p
        for i, (a, b, c) in enumerate(tri.tolist()):
            q, w, d2 = _closest_on_triangle(p.tolist(), a, b, c)
            assert q == tuple(points[i]) and w == tuple(bary[i])
            assert d2 == float((gaps[i] * gaps[i]).sum())
        assert np.abs(points - trimesh_closest(p, tri)).max() < 1e-12


def test_proxy_is_trimeshs_nearest_point_on_a_deformed_balloon():
    balloon = Balloon()
    keys = [balloon.patch_key([0, 0, R]), balloon.patch_key([0, R, 0])]
    balloon.step(keys, [3.0, 1.5])
    index = SurfaceIndex.build(balloon.rest_vertices, balloon.faces)
    current = balloon.vertices
    tri = current[balloon.faces]
    rng = np.random.default_rng(11)
    directions = rng.normal(size=(30, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    probes = list(directions * rng.uniform(R - 0.015, R + 0.01, (30, 1)))
    probes += [np.array([0.0, 0.0, R - 0.01]), np.array([0.0, R - 0.006, 0.001])]
    for probe in probes:
        s = closest_point(index, current, probe, balloon.max_displacement_m)
        reference = trimesh_closest(probe, tri)
        nearest = reference[np.argmin(np.linalg.norm(reference - probe, axis=1))]
        assert np.abs(s.point - nearest).max() < 1e-12
        assert abs(s.penetration_m) == pytest.approx(np.linalg.norm(nearest - probe), abs=1e-12)
