"""A viewer of a FEM solid with an inclusion gets the lump's rest surface on joining (``INC1``).

The room is built as ``haptic server --object fem --inclusion FILE --inclusion-material NAME``
builds it (:func:`server.main.build_world`); a viewer joins and the reference decoder
(:mod:`server.viewer_decoder`, what web/lump.js does) reads the lump back. Rooms without
inclusions send viewers exactly the frames they did before. What the server sends is bounded
however large or many the inclusions are, and a malformed ``INC1`` frame is refused.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import trimesh

from haptic_collab.server.objects.balloon import Balloon, BalloonParams
from haptic_collab.server.objects.fem import FemParams, FemSolid
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.room import Room
from haptic_collab.server.viewer_decoder import ViewerStreamDecoder, decode_inclusion
from haptic_collab.server.viewer_stream import (
    INC_HEADER,
    INCLUSION_MAGIC,
    MAX_INCLUSION_FACES,
    MAX_INCLUSION_TEXT_BYTES,
    MAX_INCLUSIONS_SENT,
    ViewerStream,
    encode_inclusions,
)
from haptic_collab.server.world import World
from haptic_collab.shared.protocol import PROTOCOL_VERSION

SIM_RATE_HZ = 20.0
LUMP_CENTRE_M = (0.0, 0.0, 0.05)
LUMP_RADIUS_M = 0.02


def join(room: Room, conn: str, role: str) -> list[Any]:
    """What ``conn`` gets on joining ``room`` as ``role``: every frame's data, in order."""
    room.connect(conn, 0.0)
    hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "role": role, "name": conn}
    return [o.data for o in room.receive(conn, json.dumps(hello), 0.0) if o.conn_id == conn]


@pytest.fixture(scope="module")
def lump_room(tmp_path_factory: pytest.TempPathFactory) -> tuple[Room, trimesh.Trimesh]:
    """A room around the default sphere (r = 0.1 m) of liver with a lump ten times as stiff,
    loaded from a file in a folder, as the server's command line loads it."""
    from haptic_collab.server.main import ServerOptions, build_world

    folder = tmp_path_factory.mktemp("private-folder")
    lump = trimesh.creation.icosphere(subdivisions=1, radius=LUMP_RADIUS_M)  # 42 vertices
    lump.apply_translation(LUMP_CENTRE_M)
    path = folder / "lump.stl"
    lump.export(path)
    opts = ServerOptions(
        object="fem",
        subdivisions=2,
        inclusions=(str(path),),
        inclusion_materials=("liver*10",),
        volume_cache=str(folder / "volumes"),
    )
    return Room(build_world(opts), SIM_RATE_HZ), lump


def test_a_viewer_of_a_fem_room_with_a_lump_gets_its_surface_and_a_user_does_not(lump_room):
    room, lump = lump_room
    user = join(room, "a", "user")
    assert [type(d) for d in user] == [str]  # the welcome only: users never get the lump
    frames = join(room, "v", "viewer")
    binaries = [d for d in frames if isinstance(d, bytes)]
    assert [b[:4] for b in binaries] == [b"FAC1", b"VTX1", b"NRM1", b"DSV1", b"INC1"]
    dec = ViewerStreamDecoder()
    for b in binaries[1:]:
        dec.feed(b)
    assert list(dec.inclusions) == [0]
    inc = dec.inclusions[0]
    assert (inc.index, inc.of) == (0, 1)
    assert inc.name == "lump.stl"  # the file's name: the server's folders stay on the server
    assert inc.material == "liver*10"
    assert inc.young_ratio == pytest.approx(10.0, rel=1e-6)
    assert not inc.decimated
    # the lump's own surface, in metres in the object's frame, closed and wound outward
    drawn = trimesh.Trimesh(inc.vertices, inc.faces, process=False)
    assert drawn.is_watertight and drawn.is_winding_consistent
    assert drawn.volume == pytest.approx(lump.volume, rel=1e-5)
    gap = np.min(np.linalg.norm(inc.vertices[:, None] - lump.vertices[None], axis=2), axis=1)
    assert float(gap.max()) < 1e-7  # each vertex is one of the file's (float32)
    assert len(inc.faces) == len(lump.faces)
    # it is inside the object the viewer draws
    assert float(np.max(np.linalg.norm(inc.vertices, axis=1))) < 0.1


def test_rooms_without_inclusions_send_viewers_the_frames_they_always_did(tmp_path: Path):
    balloon = World(Balloon(default_balloon(0.1, 2), BalloonParams(sim_period_s=1 / SIM_RATE_HZ)))
    solid = World(
        FemSolid(
            trimesh.creation.icosphere(2, 0.05),
            FemParams(sim_period_s=1 / SIM_RATE_HZ),
            cache_dir=str(tmp_path),
        )
    )
    for world, form in ((balloon, b"DSP1"), (solid, b"DSV1")):
        room = Room(world, SIM_RATE_HZ)
        frames = join(room, "v", "viewer")
        binaries = [d for d in frames if isinstance(d, bytes)]
        assert [b[:4] for b in binaries] == [b"FAC1", b"VTX1", b"NRM1", form]
        assert room._viewer_stream.inclusion_frames == ()
        n = len(world.vertices)
        assert len(binaries[1]) == 12 + 12 * n  # the rest positions, nothing appended


def surface(vertices: Any, faces: Any, name: str = "lump.stl", ratio: float = 10.0) -> Any:
    """An inclusion surface as :func:`server.objects.inclusions.inclusion_surfaces` makes."""
    return SimpleNamespace(
        name=name, material="liver*10", young_ratio=ratio, vertices=vertices, faces=faces
    )


def sphere(subdivisions: int, radius: float, centre: tuple[float, float, float]) -> Any:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return surface(mesh.vertices + np.asarray(centre), mesh.faces, name=f"r{radius}")


def test_what_the_server_sends_of_huge_or_many_inclusions_is_bounded():
    """One lump of 327 680 triangles and 19 small ones: 16 frames, at most 4096 triangles
    together; the huge one decimated to its share and still the same sphere."""
    huge = sphere(7, 0.03, (0.0, 0.0, 0.0))
    small = [sphere(1, 0.002, (0.01 * k, 0.0, 0.0)) for k in range(19)]  # 80 triangles each
    frames = encode_inclusions([huge, *small])
    assert len(frames) == MAX_INCLUSIONS_SENT
    decoded = [decode_inclusion(f) for f in frames]
    assert [d.index for d in decoded] == list(range(MAX_INCLUSIONS_SENT))
    assert all(d.of == 20 for d in decoded)
    assert sum(len(d.faces) for d in decoded) <= MAX_INCLUSION_FACES
    assert sum(len(f) for f in frames) < 100_000  # bytes, all of them together
    big = decoded[0]
    assert big.decimated and 1000 < len(big.faces) <= MAX_INCLUSION_FACES
    r = np.linalg.norm(big.vertices, axis=1)
    assert float(np.max(np.abs(r - 0.03))) < 0.003  # within a tenth of its radius
    drawn = trimesh.Trimesh(big.vertices, big.faces, process=False)
    assert drawn.volume == pytest.approx(4 / 3 * math.pi * 0.03**3, rel=0.05)
    for d in decoded[1:]:  # the small ones fit their share whole
        assert not d.decimated and len(d.faces) == 80


def test_names_are_cut_and_an_inclusion_that_cannot_be_drawn_is_left_out():
    ok = sphere(1, 0.01, (0.0, 0.0, 0.0))
    ok.name = "é" * 40  # 80 bytes of UTF-8
    bad = sphere(1, 0.01, (0.03, 0.0, 0.0))
    bad.vertices = bad.vertices.copy()
    bad.vertices[3, 0] = math.nan
    far = sphere(1, 0.01, (0.0, 0.03, 0.0))
    far.young_ratio = math.inf  # unknown: sent as NaN, read as None
    decoded = [decode_inclusion(f) for f in encode_inclusions([ok, bad, far])]
    assert [(d.index, d.of) for d in decoded] == [(0, 3), (2, 3)]
    assert decoded[0].name == "é" * (MAX_INCLUSION_TEXT_BYTES // 2)
    assert decoded[0].young_ratio == pytest.approx(10.0)
    assert decoded[1].young_ratio is None
    assert encode_inclusions([]) == []


def malformed_frames() -> dict[str, bytes]:
    """A valid ``INC1`` frame, and the same broken in each way a viewer must refuse."""
    (good,) = encode_inclusions([sphere(1, 0.01, (0.0, 0.0, 0.0))])
    head = list(INC_HEADER.unpack_from(good))
    body = good[INC_HEADER.size :]
    text = head[7] + head[8] + (-(head[7] + head[8]) % 4)

    def with_header(**changes: Any) -> bytes:
        h = head.copy()
        names = ["magic", "index", "of", "k", "m", "ratio", "flags", "nb", "mb"]
        for key, value in changes.items():
            h[names.index(key)] = value
        return INC_HEADER.pack(*h) + body

    nan_vertex = bytearray(good)
    nan_vertex[INC_HEADER.size + text : INC_HEADER.size + text + 4] = b"\x00\x00\xc0\x7f"
    far_vertex = bytearray(good)
    far_vertex[INC_HEADER.size + text : INC_HEADER.size + text + 4] = np.float32(5e3).tobytes()
    bad_index = bytearray(good)
    bad_index[-2:] = np.uint16(head[3]).tobytes()  # the last corner: one past the last vertex
    return {
        "good": good,
        "truncated": good[:-2],
        "short": good[:20],
        "magic": with_header(magic=b"INC2"),
        "index beyond of": with_header(index=1, of=1),
        "too many faces": with_header(m=MAX_INCLUSION_FACES + 1),
        "counts disagree with length": with_header(k=head[3] + 1),
        "long text": with_header(nb=MAX_INCLUSION_TEXT_BYTES + 4),
        "nan vertex": bytes(nan_vertex),
        "vertex 5 km away": bytes(far_vertex),
        "triangle index out of range": bytes(bad_index),
    }


def test_the_reference_decoder_refuses_malformed_inclusion_frames():
    frames = malformed_frames()
    frames_good = frames.pop("good")
    assert decode_inclusion(frames_good).faces.shape == (80, 3)
    for what, frame in frames.items():
        with pytest.raises(ValueError, match="INC1"):
            decode_inclusion(frame)
        if frame[:4] != INCLUSION_MAGIC:
            continue  # another magic is not an inclusion to the stream's decoder
        # the stream's decoder refuses it too, and keeps the inclusion it had
        dec = ViewerStreamDecoder()
        dec.feed(frames_good)
        with pytest.raises(ValueError, match="INC1"):
            dec.feed(frame)
        assert list(dec.inclusions) == [0], what


def test_a_solid_sagging_under_its_weight_has_its_lump_drawn_where_the_sag_holds_it(lump_room):
    """With ``--gravity`` the solid's rest state is the sagged one: the lump is sent moved by
    its nodes' sag (here a made-up sag of 3 mm down on the same solid)."""
    room, lump = lump_room
    obj = room.world.obj
    sag = np.zeros_like(obj.nodes)
    sag[:, 2] = -0.003
    sagged = SimpleNamespace(
        rest_vertices=obj.rest_vertices,
        rest_normals=obj.rest_normals,
        nodes=obj.nodes,
        tets=obj.tets,
        materials=obj.materials,
        sag_nodes=sag,
        tangential_motion=True,
    )
    world = SimpleNamespace(obj=sagged, vertices=obj.rest_vertices, faces=room.world.faces)
    (frame,) = ViewerStream.of_world(world, SIM_RATE_HZ).inclusion_frames
    inc = decode_inclusion(frame)
    centre = inc.vertices.mean(axis=0)
    np.testing.assert_allclose(centre, np.asarray(LUMP_CENTRE_M) + (0, 0, -0.003), atol=1e-6)
