"""The viewer stream: what a viewer decodes is the server's surface, at a fraction of the bytes.

Sans-I/O: frames go through a simulated link that drops, replaces and delays them the way the
asyncio layer may (latest-wins queue, injected loss and latency), and the reference decoder
(what web/viewer.js does) checks the surface after every frame it gets. The balloon's vertices
move along their normals (``DSP1``); a solid whose vertices also slide sideways (the FEM solid,
or a synthetic motion) gets vectors (``DSV1``), checked the same way per axis. At the end, tests
drive the room with the real balloon and the real FEM solid, and one runs a viewer over real
websockets.
"""

from __future__ import annotations

import asyncio
import json
from collections import deque

import numpy as np
import pytest
import trimesh

from haptic_collab.server.objects.balloon import Balloon, BalloonParams
from haptic_collab.server.objects.fem import FemParams, FemSolid
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.room import Room
from haptic_collab.server.viewer_decoder import ViewerStreamDecoder, decode_displacement
from haptic_collab.server.viewer_stream import (
    BASE_QUANTUM_NM,
    DSP_HEADER,
    FLAG_CLAMPED,
    FLAG_DENSE,
    FLAG_INDEX32,
    FLAG_KEY,
    FLAG_PARTIAL,
    Frame,
    ViewerStream,
    vertex_normals,
)
from haptic_collab.server.world import ContactInput, World
from haptic_collab.shared.protocol import PROTOCOL_VERSION, State, decode_binary, encode

QUANTUM_M = BASE_QUANTUM_NM * 1e-9
#: float32 rest positions and normals add a few nm on top of the half-quantum rounding
TOL_M = QUANTUM_M + 1e-8
SIM_RATE_HZ = 20.0


def sphere(n_sub: int = 2) -> tuple[np.ndarray, np.ndarray]:
    mesh = default_balloon(0.1, n_sub)
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces)


def stream_and_decoder(
    rest: np.ndarray, faces: np.ndarray, budget: int | None = None, w0: np.ndarray | None = None
) -> tuple[ViewerStream, ViewerStreamDecoder, np.ndarray]:
    normals = vertex_normals(rest, faces)
    stream = ViewerStream(rest, normals, frame_budget_bytes=budget)
    w = np.zeros(len(rest)) if w0 is None else w0
    dec = ViewerStreamDecoder()
    for f in stream.join("v", 0, rest + w[:, None] * normals):
        dec.feed(f)
    return stream, dec, normals


def surface_error_m(dec: ViewerStreamDecoder, vertices: np.ndarray) -> float:
    return float(np.max(np.linalg.norm(dec.vertices - vertices, axis=1)))


def press(world: World, top: np.ndarray, force_n: float) -> None:
    world.tick({"a": ContactInput(probe=top - [0, 0, 0.002], force=np.array([0, 0, force_n]))})


def pressed_frame(world, top, force, stream, dec, k, budget):  # type: ignore[no-untyped-def]
    """Press ``world`` at ``top`` with ``force`` [N] (:func:`press`), stream tick ``k`` to viewer
    ``v`` and feed its frame to ``dec``: the frame, checked to fit ``budget`` bytes and to flag
    itself partial exactly when it is."""
    press(world, top, force)
    f = stream.frames(k, world.vertices, ["v"])["v"]
    f.sent()
    dec.feed(f.data)
    assert len(f.data) <= budget
    assert f.partial == bool(decode_displacement(f.data).flags & FLAG_PARTIAL)
    return f


def press_profile() -> list[float]:
    """Force [N] per tick: rest, a 1.5 s ramp to 4 N (about 13 mm at the top), hold, release."""
    return [0.0] * 5 + list(np.linspace(0.0, 4.0, 30)) + [4.0] * 10 + list(np.linspace(4, 0, 10))


@pytest.fixture
def balloon_world() -> World:
    return World(Balloon(default_balloon(0.1, 3), BalloonParams(sim_period_s=1 / SIM_RATE_HZ)))


# ----------------------------------------------------------------------------- exactness
def test_viewer_sees_the_pressed_balloon_within_one_quantum_after_every_frame(balloon_world):
    world = balloon_world
    top = world.obj.rest_vertices[np.argmax(world.obj.rest_vertices[:, 2])]
    stream = ViewerStream(world.obj.rest_vertices, world.obj.rest_normals)
    dec = ViewerStreamDecoder()
    for f in stream.join("v", 0, world.vertices):
        dec.feed(f)
    deepest = 0.0
    for k, force in enumerate(press_profile(), start=1):
        press(world, top, force)
        frame = stream.frames(k, world.vertices, ["v"])["v"]
        frame.sent()
        dec.feed(frame.data)
        assert dec.tick == k
        assert surface_error_m(dec, world.vertices) <= TOL_M, k
        deepest = min(deepest, float(np.min(dec.w)))
    assert deepest < -0.010  # the test saw a real dent (more than 10 mm)


def test_join_mid_press_gets_the_current_dent_in_its_keyframe(balloon_world):
    world = balloon_world
    top = world.obj.rest_vertices[np.argmax(world.obj.rest_vertices[:, 2])]
    for _ in range(3):
        press(world, top, 3.0)
    stream = ViewerStream(world.obj.rest_vertices, world.obj.rest_normals)
    frames = stream.join("late", 7, world.vertices)
    assert [f[:4] for f in frames[:2]] == [b"VTX1", b"NRM1"]
    assert decode_binary(frames[0])[1] == 0  # the rest positions, a plain VTX1 frame
    key = decode_displacement(frames[2])
    assert key.flags & FLAG_KEY and key.flags & FLAG_DENSE and key.tick == 7
    dec = ViewerStreamDecoder()
    for f in frames:
        dec.feed(f)
    assert np.min(dec.w) < -0.005
    assert surface_error_m(dec, world.vertices) <= TOL_M


# ----------------------------------------------------------------------------- bytes
def test_a_balloon_at_rest_costs_a_header_per_tick(balloon_world):
    world = balloon_world
    stream = ViewerStream.of_world(world, SIM_RATE_HZ)
    stream.join("v", 0, world.vertices)
    sizes = []
    for k in range(1, 41):
        world.tick({})
        f = stream.frames(k, world.vertices, ["v"])["v"]
        f.sent()
        sizes.append(len(f.data))
    assert sizes == [DSP_HEADER.size] * 40
    assert sum(sizes) / 2.0 <= 500  # bytes per second at 20 Hz: about nothing


def test_after_a_press_is_released_the_stream_goes_quiet_again(balloon_world):
    world = balloon_world
    top = world.obj.rest_vertices[np.argmax(world.obj.rest_vertices[:, 2])]
    stream = ViewerStream.of_world(world, SIM_RATE_HZ)
    stream.join("v", 0, world.vertices)
    counts = []
    for k, force in enumerate([*press_profile(), *[0.0] * 10], start=1):
        press(world, top, force)
        f = stream.frames(k, world.vertices, ["v"])["v"]
        f.sent()
        counts.append(f.count)
    assert max(counts) > 100  # the press was streamed
    assert counts[-5:] == [0] * 5


def test_a_frame_never_exceeds_the_budget_and_catches_up_once_the_motion_stops(balloon_world):
    world = balloon_world
    top = world.obj.rest_vertices[np.argmax(world.obj.rest_vertices[:, 2])]
    budget = 600  # bytes: about 145 of the 642 vertices per frame
    stream = ViewerStream(world.obj.rest_vertices, world.obj.rest_normals, budget)
    dec = ViewerStreamDecoder()
    for data in stream.join("v", 0, world.vertices):
        dec.feed(data)
    partial = 0
    ramp = [0.0] * 2 + list(np.linspace(0.0, 4.0, 20))
    for k, force in enumerate(ramp + [4.0] * 10, start=1):
        f = pressed_frame(world, top, force, stream, dec, k, budget)
        partial += f.partial
        if k == len(ramp):  # the largest changes go first: the dent itself is never far behind
            err = np.abs(dec.w - stream.displacement(world.vertices))
            assert err.max() < 0.1 * np.abs(dec.w).max()
    assert partial > 5  # the budget really held changes back during the ramp
    assert surface_error_m(dec, world.vertices) <= TOL_M  # and the viewer caught up in the hold


# ----------------------------------------------------------------------------- a lossy link
class Link:
    """The asyncio layer as the encoder sees it: frames of one viewer, in order, some dropped.

    A frame waits ``delay`` ticks in flight; a newer one may replace an older one still queued
    (latest wins), or be lost (injected loss). A frame is reported ``sent`` when it is written,
    then decoded.
    """

    def __init__(self, rng: np.random.Generator, loss: float, replace: float, delay: int) -> None:
        self.rng, self.loss, self.replace, self.delay = rng, loss, replace, delay
        self.queue: deque[tuple[int, int, Frame]] = deque()  # (due tick, tick made, frame)

    def push(self, now: int, frame: Frame) -> None:
        if self.rng.random() < self.loss:
            return
        if self.queue and self.rng.random() < self.replace:
            self.queue.pop()  # the newer frame of the stream replaces the queued one
        self.queue.append((now + int(self.rng.integers(0, self.delay + 1)), now, frame))

    def deliver(self, now: int) -> list[tuple[int, Frame]]:
        out = []
        while self.queue and self.queue[0][0] <= now:
            _, made, frame = self.queue.popleft()
            frame.sent()
            out.append((made, frame))
        return out


def random_smooth_field(rng: np.random.Generator, rest: np.ndarray, amplitude_m: float):
    c = rng.normal(size=3)
    c /= np.linalg.norm(c)
    d = np.linalg.norm(rest / np.linalg.norm(rest, axis=1, keepdims=True) - c, axis=1)
    return -amplitude_m * np.exp(-((d / rng.uniform(0.2, 0.8)) ** 2))


def random_step(rng: np.random.Generator, rest: np.ndarray, w: np.ndarray, earlier: np.ndarray):
    """The next displacement: a dent moves in, a few vertices wiggle, or an earlier shape returns."""
    kind = rng.integers(0, 4)
    if kind == 0:
        return random_smooth_field(rng, rest, rng.uniform(0.0005, 0.02))
    if kind == 1:
        idx = rng.choice(len(rest), 10, replace=False)
        w = w.copy()
        w[idx] += rng.normal(0, 2e-4, 10)
        return w
    if kind == 2:
        return earlier
    return w


#: viewer -> (loss, replace, delay in ticks, tick it joins at)
LINKS = {
    "ideal": (0.0, 0.0, 0, 0),
    "drops": (0.3, 0.0, 0, 0),
    "lossy": (0.2, 0.5, 3, 0),
    "late": (0.1, 0.3, 1, 100),
}


@pytest.mark.parametrize("seed", range(6))
def test_dropped_replaced_and_delayed_frames_never_leave_a_viewer_wrong(seed):
    rng = np.random.default_rng(seed)
    rest, faces = sphere(2)
    normals = vertex_normals(rest, faces)
    stream = ViewerStream(rest, normals)
    links = {v: Link(rng, *LINKS[v][:3]) for v in LINKS}
    decoders: dict[str, ViewerStreamDecoder] = {}
    history = {0: np.zeros(len(rest))}
    w = history[0]
    checked = 0
    for k in range(1, 300):
        for v, (*_, joins) in LINKS.items():
            if joins == k - 1:
                decoders[v] = ViewerStreamDecoder()
                for f in stream.join(v, k - 1, rest + w[:, None] * normals):
                    decoders[v].feed(f)
        w = history[k] = random_step(rng, rest, w, history[max(0, k - int(rng.integers(1, 5)))])
        for v, frame in stream.frames(k, rest + w[:, None] * normals, list(decoders)).items():
            links[v].push(k, frame)
        for v in decoders:
            for made, frame in links[v].deliver(k):
                decoders[v].feed(frame.data)
                truth = rest + history[made][:, None] * normals
                assert surface_error_m(decoders[v], truth) <= TOL_M, (seed, v, k, made)
                checked += 1
    assert checked > 300


def catch_up_over_poor_links(  # type: ignore[no-untyped-def]
    rng, stream, state, step, place, budget
):
    """200 ticks of ``stream`` to the viewers of :data:`LINKS`, each joining at its tick over
    its lossy link; the surface at ``place(state)`` moves by ``state = step(state)`` for 149
    ticks, then stands still over perfect links; every frame within ``budget`` bytes.

    Returns (the decoders by viewer, the last state, how many frames were partial)."""
    links = {v: Link(rng, *LINKS[v][:3]) for v in LINKS}
    decoders: dict[str, ViewerStreamDecoder] = {}
    partial = 0
    for k in range(1, 200):
        for v, (*_, joins) in LINKS.items():
            if joins == k - 1:
                decoders[v] = ViewerStreamDecoder()
                for f in stream.join(v, k - 1, place(state)):
                    decoders[v].feed(f)
        if k < 150:  # moving over a poor link, then still over a perfect one
            state = step(state)
        elif k == 150:
            for link in links.values():
                link.loss = link.replace = link.delay = 0
        for v, frame in stream.frames(k, place(state), list(decoders)).items():
            assert len(frame.data) <= budget
            partial += frame.partial
            links[v].push(k, frame)
        for v in decoders:
            for _, frame in links[v].deliver(k):
                decoders[v].feed(frame.data)
    return decoders, state, partial


@pytest.mark.parametrize("seed", range(3))
def test_under_a_budget_every_viewer_catches_up_once_the_surface_stops(seed):
    rng = np.random.default_rng(seed)
    rest, faces = sphere(2)
    normals = vertex_normals(rest, faces)
    budget = 200  # 45 of the 162 vertices per frame
    stream = ViewerStream(rest, normals, budget)
    decoders, w, partial = catch_up_over_poor_links(
        rng, stream, np.zeros(len(rest)), lambda w: random_step(rng, rest, w, w),
        lambda w: rest + w[:, None] * normals, budget,
    )  # fmt: skip
    assert partial > 20
    for v, dec in decoders.items():
        assert surface_error_m(dec, rest + w[:, None] * normals) <= TOL_M, v


def test_a_stalled_viewer_costs_bounded_memory_and_recovers():
    rng = np.random.default_rng(1)
    rest, faces = sphere(2)
    stream, dec, normals = stream_and_decoder(rest, faces)
    stuck: Frame | None = None
    w = np.zeros(len(rest))
    for k in range(1, 60):  # the socket is stuck writing frame 1; later ones replace each other
        w = random_smooth_field(rng, rest, 0.01)
        f = stream.frames(k, rest + w[:, None] * normals, ["v"])["v"]
        stuck = stuck or f
    assert stuck is not None
    stuck.sent()  # the old frame finally goes out
    dec.feed(stuck.data)
    f = stream.frames(60, rest + w[:, None] * normals, ["v"])["v"]
    f.sent()
    dec.feed(f.data)
    assert surface_error_m(dec, rest + w[:, None] * normals) <= TOL_M
    assert len(stream._viewers["v"].in_flight) <= stream.max_in_flight


def test_viewers_that_left_are_forgotten_and_each_viewer_has_its_own_state():
    rest, faces = sphere(1)
    normals = vertex_normals(rest, faces)
    stream = ViewerStream(rest, normals)
    stream.join("a", 0, rest)
    stream.join("b", 0, rest)
    moved = rest + 0.003 * normals
    fa = stream.frames(1, moved, ["a", "b"])
    fa["a"].sent()  # b's frame was dropped: b gets the change again, a does not
    again = stream.frames(2, moved, ["a", "b"])
    assert again["a"].count == 0 and again["b"].count == len(rest)
    stream.frames(3, moved, ["b"])
    assert stream.viewers == ["b"]


# ----------------------------------------------------------------------------- scale and format
def assert_quantum_follows_the_amplitude(  # type: ignore[no-untyped-def]
    stream, dec, rest, move, expected, decoded, huge_direction
) -> None:
    """Deform by ``amp * move`` for amplitudes of 50, 200 and 2 mm: the frame's quantum doubles
    from 1 um as far as int16 needs and comes back, and ``decoded()`` (what the viewer holds)
    equals ``amp * expected`` within half a quantum; a 5 km deformation is flagged clamped."""
    for k, amp in enumerate((0.050, 0.200, 0.002), start=1):
        f = stream.frames(k, rest + amp * move, ["v"])["v"]
        f.sent()
        dec.feed(f.data)
        q = decode_displacement(f.data).quantum_m
        assert q == pytest.approx({1: 2e-6, 2: 8e-6, 3: 1e-6}[k])
        assert np.max(np.abs(decoded() - amp * expected)) <= q / 2 + 1e-12
    huge = stream.frames(9, rest + 5e3 * huge_direction, ["v"])["v"]
    assert decode_displacement(huge.data).flags & FLAG_CLAMPED


def test_a_deformation_beyond_int16_micrometres_doubles_the_quantum_and_comes_back():
    rest, faces = sphere(1)
    stream, dec, normals = stream_and_decoder(rest, faces)
    w = np.linspace(-1.0, 1.0, len(rest))
    assert_quantum_follows_the_amplitude(
        stream, dec, rest, w[:, None] * normals, w, lambda: dec.w, normals
    )


def test_large_meshes_use_32_bit_indices_and_bad_frames_are_refused():
    n = 70_000
    rest = np.column_stack([np.arange(n) * 1e-3, np.zeros(n), np.zeros(n)])
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    stream = ViewerStream(rest, normals)
    stream.join("v", 0, rest)
    moved = rest.copy()
    moved[[5, 69_999], 2] = [0.001, -0.002]
    d = decode_displacement(stream.frames(1, moved, ["v"])["v"].data)
    assert d.index is not None and list(d.index) == [5, 69_999]
    assert list(d.values) == [1000, -2000]
    with pytest.raises(ValueError):
        decode_displacement(b"DSP1" + b"\x00" * 8)
    with pytest.raises(ValueError):
        decode_displacement(DSP_HEADER.pack(b"DSP1", 0, 3, 1000, 0) + b"\x00" * 4)
    with pytest.raises(ValueError):
        ViewerStream(rest, normals[:-1])


# ----------------------------------------------------------------------------- the room
def room_with_user_and_viewer(world: World) -> tuple[Room, list[bytes]]:
    """A room around ``world`` that user ``a`` and then viewer ``v`` joined at 0 s, and the
    binary frames the viewer got on joining."""
    room = Room(world, SIM_RATE_HZ)
    for conn, role in (("a", "user"), ("v", "viewer")):
        room.connect(conn, 0.0)
        hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "role": role, "name": conn}
        outs = room.receive(conn, json.dumps(hello), 0.0)
    return room, [o.data for o in outs if isinstance(o.data, bytes)]


def test_room_streams_displacements_to_a_viewer_that_reports_what_was_sent():
    world = World(Balloon(default_balloon(0.1, 2), BalloonParams(sim_period_s=1 / SIM_RATE_HZ)))
    room, binaries = room_with_user_and_viewer(world)
    top = room.object_info.top_m
    dec = ViewerStreamDecoder()
    assert [b[:4] for b in binaries] == [b"FAC1", b"VTX1", b"NRM1", b"DSP1"]
    for b in binaries[1:]:
        dec.feed(b)
    sizes = []
    for k in range(1, 40):
        state = {
            "type": "state",
            "seq": k,
            "probe_m": [top[0], top[1], top[2] - 0.004],
            "force_n": [0.0, 0.0, min(2.0, 0.1 * k)],
            "k_h": 300.0,
            "i_gain": 3000.0,
        }
        room.receive("a", json.dumps(state), k * 0.05 - 0.01)
        (vout,) = [o for o in room.tick(k, k * 0.05) if o.conn_id == "v" and o.stream == "vertices"]
        assert isinstance(vout.data, bytes) and vout.on_sent is not None
        vout.on_sent()
        dec.feed(vout.data)
        sizes.append(len(vout.data))
        assert surface_error_m(dec, world.vertices) <= TOL_M
    assert np.min(dec.w) < -0.003
    assert sizes[-1] == DSP_HEADER.size  # the press is held: nothing more to send


# ----------------------------------------------------------------------------- over websockets
@pytest.mark.timeout(60)
async def test_a_viewer_over_websockets_decodes_the_servers_surface():
    from websockets.asyncio.client import connect

    from haptic_collab.server.app import ServerApp

    world = World(Balloon(default_balloon(0.1, 3), BalloonParams(sim_period_s=1 / SIM_RATE_HZ)))
    app = ServerApp(Room(world, SIM_RATE_HZ), "127.0.0.1", 0)
    await app.start()
    dec = ViewerStreamDecoder()
    sizes: list[int] = []
    try:
        url = f"ws://127.0.0.1:{app.port}/ws"
        # neither connection reads to the end (the user reads only its welcome): unbounded
        # queues keep their readers taking frames, so a close handshake does not wait out
        # close_timeout (10 s) behind unread patches
        async with (
            connect(url, max_queue=None) as user,
            connect(url, max_queue=None) as viewer,
        ):
            hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "name": "A"}
            await user.send(json.dumps({**hello, "role": "user"}))
            top = json.loads(await user.recv())["object"]["top_m"]
            await viewer.send(json.dumps({**hello, "name": "V", "role": "viewer"}))
            loop = asyncio.get_running_loop()
            end = loop.time() + 2.5
            seq = 0
            while loop.time() < end:
                seq += 1
                force = min(2.0, 0.1 * seq)  # ramps up over 1 s, then a steady press
                probe = (top[0], top[1], top[2] - 0.004)
                state = State(
                    seq=seq, probe_m=probe, force_n=(0.0, 0.0, force), k_h=300.0, i_gain=3000.0
                )
                await user.send(encode(state))
                deadline = loop.time() + 0.05
                while (left := deadline - loop.time()) > 0:
                    try:
                        frame = await asyncio.wait_for(viewer.recv(), left)
                    except TimeoutError:
                        break
                    if isinstance(frame, bytes):
                        dec.feed(frame)
                        sizes.append(len(frame))
            server_vertices = app.room.world.vertices.copy()
    finally:
        await app.stop()
    assert np.min(dec.w) < -0.003  # the viewer saw the dent
    assert surface_error_m(dec, server_vertices) <= TOL_M
    # while the press is held, the frames are empty: the rest of the bytes went into the press
    assert sizes[-5:] == [DSP_HEADER.size] * 5


# ----------------------------------------------------------------------------- the balloon's form
def test_the_balloon_keeps_normal_displacements_at_four_bytes_a_changed_vertex(balloon_world):
    """The balloon moves only along its normals: it gets DSP1, 2 bytes a vertex in a dense frame
    and 4 (index + value) in a sparse one, never the three values a vertex of DSV1."""
    world = balloon_world
    assert Balloon.tangential_motion is False
    top = world.obj.rest_vertices[np.argmax(world.obj.rest_vertices[:, 2])]
    n = world.n_vertices
    for budget in (None, 1024):  # unlimited: mostly dense; 1024 bytes: a dense frame never fits
        stream = ViewerStream.of_world(world, SIM_RATE_HZ, None if budget is None else budget * 20)
        assert not stream.vector and stream.frame_budget_bytes == budget
        key = stream.join("v", 0, world.vertices)[2]
        assert key[:4] == b"DSP1" and len(key) == DSP_HEADER.size + 2 * n
        kinds = set()
        for k, force in enumerate(press_profile(), start=1):
            press(world, top, force)
            f = stream.frames(k, world.vertices, ["v"])["v"]
            f.sent()
            assert f.data[:4] == b"DSP1"
            assert len(f.data) == DSP_HEADER.size + (2 * n if f.dense else 4 * f.count)
            kinds.add("dense" if f.dense else "sparse" if f.count else "empty")
        assert kinds == ({"dense", "empty"} if budget is None else {"sparse", "empty"})


# ----------------------------------------------------------------------------- vectors: the solid
def axis_error_m(dec: ViewerStreamDecoder, vertices: np.ndarray) -> float:
    """Largest difference on any axis [m] between the decoded surface and ``vertices``."""
    return float(np.max(np.abs(dec.vertices - vertices)))


def sideways_m(rest: np.ndarray, normals: np.ndarray, vertices: np.ndarray) -> float:
    """Largest displacement [m] off the rest normal: what a DSP1 viewer would draw wrong."""
    d = vertices - rest
    along = np.einsum("ij,ij->i", d, normals)[:, None] * normals
    return float(np.max(np.linalg.norm(d - along, axis=1)))


@pytest.fixture(scope="module")
def volume_cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("volumes"))


@pytest.fixture
def fem_world(volume_cache) -> World:
    """A 162-vertex FEM ball (r = 5 cm, healthy liver) whose base is held: P2 on the
    42-vertex icosphere, shown split four ways."""
    mesh = trimesh.creation.icosphere(1, 0.05)
    params = FemParams(sim_period_s=1 / SIM_RATE_HZ)
    return World(FemSolid(mesh, params, cache_dir=volume_cache))


def fem_press_profile() -> list[float]:
    """Force [N] per tick on the FEM ball: rest, a 1 s ramp to 1 N, hold, release, rest."""
    return [0.0] * 3 + list(np.linspace(0.0, 1.0, 20)) + [1.0] * 15 + [0.0] * 25


def test_the_room_streams_the_fem_solid_as_vectors_within_a_quantum_per_axis(fem_world):
    """A user presses the FEM solid, whose surface also slides sideways: the viewer gets DSV1
    (keyframe on join, then frames) and after every frame its surface is the server's within a
    quantum on each axis, though vertices moved over a millimetre off their normals."""
    world = fem_world
    assert FemSolid.tangential_motion is True
    room, binaries = room_with_user_and_viewer(world)
    top = room.object_info.top_m
    assert [b[:4] for b in binaries] == [b"FAC1", b"VTX1", b"NRM1", b"DSV1"]
    key = decode_displacement(binaries[3])
    assert key.vector and key.flags & FLAG_KEY and key.flags & FLAG_DENSE
    assert key.values.shape == (world.n_vertices, 3)
    dec = ViewerStreamDecoder()
    for b in binaries[1:]:
        dec.feed(b)
    obj = world.obj
    sideways = 0.0
    for k, force in enumerate(fem_press_profile(), start=1):
        probe = (top[0], top[1], top[2] - 0.004)
        state = State(seq=k, probe_m=probe, force_n=(0.0, 0.0, force), k_h=100.0, i_gain=1000.0)
        room.receive("a", encode(state), k * 0.05 - 0.01)
        (vout,) = [o for o in room.tick(k, k * 0.05) if o.conn_id == "v" and o.stream == "vertices"]
        assert isinstance(vout.data, bytes) and vout.data[:4] == b"DSV1"
        assert vout.on_sent is not None
        vout.on_sent()
        dec.feed(vout.data)
        assert axis_error_m(dec, world.vertices) <= TOL_M, k
        sideways = max(sideways, sideways_m(obj.rest_vertices, obj.rest_normals, world.vertices))
    assert sideways > 1e-3  # drawn along the normals, the surface would be this far off
    assert np.max(np.abs(dec.displacement - obj.displacement)) <= TOL_M


def test_the_fem_solid_under_a_small_budget_is_exact_once_the_motion_stops(fem_world):
    """Under a 300-byte budget (35 of 162 vertices a frame) the press is cut into PARTIAL frames,
    the largest moves first; once the solid stops moving the viewer is exact per axis."""
    world = fem_world
    obj = world.obj
    top = obj.rest_vertices[np.argmax(obj.rest_vertices[:, 2])]
    budget = 300
    stream = ViewerStream.of_world(world, SIM_RATE_HZ, budget * SIM_RATE_HZ)
    assert stream.vector and stream.frame_budget_bytes == max(1024, budget)
    stream = ViewerStream(obj.rest_vertices, obj.rest_normals, budget, vector=True)
    dec = ViewerStreamDecoder()
    for data in stream.join("v", 0, world.vertices):
        dec.feed(data)
    partial = 0
    for k, force in enumerate(fem_press_profile()[:23], start=1):  # rest, then the ramp
        f = pressed_frame(world, top, force, stream, dec, k, budget)
        partial += f.partial
    # the largest changes go first: mid-ramp the most displaced vertex is never far behind
    moved = np.linalg.norm(obj.displacement, axis=1)
    lag = np.linalg.norm(dec.displacement - obj.displacement, axis=1)
    assert lag.max() < 0.2 * moved.max() and lag[np.argmax(moved)] < 0.05 * moved.max()
    assert partial > 5
    for k in range(24, 24 + 60):  # held still: the solid settles, the viewer catches up
        press(world, top, 1.0)
        f = stream.frames(k, world.vertices, ["v"])["v"]
        f.sent()
        dec.feed(f.data)
    assert sideways_m(obj.rest_vertices, obj.rest_normals, world.vertices) > 1e-3
    assert axis_error_m(dec, world.vertices) <= TOL_M


# ----------------------------------------------------------------------------- vectors: any motion
def random_vector_step(
    rng: np.random.Generator, rest: np.ndarray, d: np.ndarray, earlier: np.ndarray
) -> np.ndarray:
    """The next (n, 3) displacement, mostly off the normals: the body swings about an axis, a
    blob slides sideways, a few vertices wiggle, or an earlier shape returns."""
    kind = rng.integers(0, 5)
    if kind == 0:  # a swing about a random axis through the centre (an arc: modal warping)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        return np.sin(rng.uniform(-0.3, 0.3)) * np.cross(axis, rest)
    if kind == 1:  # a blob slides in a random direction
        c = rng.normal(size=3)
        c /= np.linalg.norm(c)
        dist = np.linalg.norm(rest / np.linalg.norm(rest, axis=1, keepdims=True) - c, axis=1)
        shift = rng.normal(size=3) * rng.uniform(0.0005, 0.01)
        return d + np.exp(-((dist / rng.uniform(0.2, 0.8)) ** 2))[:, None] * shift
    if kind == 2:
        idx = rng.choice(len(rest), 10, replace=False)
        d = d.copy()
        d[idx] += rng.normal(0, 2e-4, (10, 3))
        return d
    if kind == 3:
        return earlier
    return d


@pytest.mark.parametrize("seed", range(4))
def test_dropped_replaced_and_delayed_vector_frames_never_leave_a_viewer_wrong(seed):
    rng = np.random.default_rng(seed)
    rest, faces = sphere(2)
    stream = ViewerStream(rest, vertex_normals(rest, faces), vector=True, max_in_flight=3)
    links = {v: Link(rng, *LINKS[v][:3]) for v in LINKS}
    decoders: dict[str, ViewerStreamDecoder] = {}
    history = {0: np.zeros_like(rest)}
    d = history[0]
    checked = sideways = 0.0
    for k in range(1, 300):
        for v, (*_, joins) in LINKS.items():
            if joins == k - 1:
                decoders[v] = ViewerStreamDecoder()
                for f in stream.join(v, k - 1, rest + d):
                    decoders[v].feed(f)
        earlier = history[max(0, k - int(rng.integers(1, 5)))]
        d = history[k] = random_vector_step(rng, rest, d, earlier)
        sideways = max(sideways, sideways_m(rest, stream.rest_normals, rest + d))
        for v, frame in stream.frames(k, rest + d, list(decoders)).items():
            assert frame.data[:4] == b"DSV1"
            links[v].push(k, frame)
        for v in decoders:
            for made, frame in links[v].deliver(k):
                decoders[v].feed(frame.data)
                assert axis_error_m(decoders[v], rest + history[made]) <= TOL_M, (seed, v, k, made)
                checked += 1
    assert checked > 300 and sideways > 0.01


@pytest.mark.parametrize("seed", range(3))
def test_under_a_budget_every_vector_viewer_catches_up_once_the_surface_stops(seed):
    rng = np.random.default_rng(seed)
    rest, faces = sphere(2)
    budget = 300  # 35 of the 162 vertices per frame (8 bytes each)
    stream = ViewerStream(rest, vertex_normals(rest, faces), budget, vector=True)
    decoders, d, partial = catch_up_over_poor_links(
        rng, stream, np.zeros_like(rest), lambda d: random_vector_step(rng, rest, d, d),
        lambda d: rest + d, budget,
    )  # fmt: skip
    assert partial > 20
    for v, dec in decoders.items():
        assert axis_error_m(dec, rest + d) <= TOL_M, v


def test_vectors_beyond_int16_micrometres_double_the_quantum_and_come_back():
    rest, faces = sphere(1)
    normals = vertex_normals(rest, faces)
    stream = ViewerStream(rest, normals, vector=True)
    dec = ViewerStreamDecoder()
    for f in stream.join("v", 0, rest):
        dec.feed(f)
    tangent = np.cross(normals, [0.3, 0.4, 1.0])  # off the normals everywhere on the sphere
    shape = np.linspace(-1, 1, len(rest))[:, None] * tangent
    shape /= np.abs(shape).max()  # the largest |d| on any axis is the amplitude
    assert_quantum_follows_the_amplitude(
        stream, dec, rest, shape, shape, lambda: dec.displacement, tangent
    )


def test_vector_frames_carry_three_int16_a_vertex_and_bad_ones_are_refused():
    n = 70_000
    rest = np.column_stack([np.arange(n) * 1e-3, np.zeros(n), np.zeros(n)])
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    stream = ViewerStream(rest, normals, vector=True)
    stream.join("v", 0, rest)
    moved = rest.copy()
    moved[5] += [0.001, -0.002, 0.0]  # sideways only: no normal component
    moved[69_999] += [0.0, 0.0, 0.003]
    f = stream.frames(1, moved, ["v"])["v"]
    assert len(f.data) == DSP_HEADER.size + 2 * (4 + 6)
    d = decode_displacement(f.data)
    assert d.vector and d.flags & FLAG_INDEX32
    assert d.index is not None and list(d.index) == [5, 69_999]
    assert d.values.tolist() == [[1000, -2000, 0], [0, 0, 3000]]
    with pytest.raises(ValueError):  # a DSP1 body length under a DSV1 header
        decode_displacement(DSP_HEADER.pack(b"DSV1", 0, 2, 1000, 0) + b"\x00" * 8)
    with pytest.raises(ValueError):
        decode_displacement(DSP_HEADER.pack(b"DSV1", 0, 2, 1000, FLAG_DENSE) + b"\x00" * 4)
    with pytest.raises(ValueError):
        decode_displacement(DSP_HEADER.pack(b"DSX1", 0, 0, 1000, 0))
    with pytest.raises(ValueError):  # a budget that cannot hold two vector entries
        ViewerStream(rest, normals, frame_budget_bytes=DSP_HEADER.size + 8, vector=True)
