"""The viewer stream: the deforming surface as quantised displacements, sent when changed.

Why one module: it is one encoder, whose quantisation (:class:`Snapshot`), frame format and
per-viewer record of what each viewer holds share their constants and state, and this docstring
is the stream's specification; the viewer's side, the decoder, is :mod:`server.viewer_decoder`.

A viewer gets the surface as displacements from the rest positions, in one of two forms; the
server picks one per object (:meth:`ViewerStream.of_world`, from the object's
``tangential_motion`` marker) and keeps it for the object's life:

- **normal** (``DSP1``, the default): one value per vertex, the displacement ``w`` [m] along the
  vertex's rest normal, outward positive. The surface the viewer draws is
  ``rest + w * rest_normal``, exactly the water balloon's own state
  (:mod:`server.objects.balloon`, ``tangential_motion = False``): its vertices move only along
  their rest normals.
- **vector** (``DSV1``): three values per vertex, the full displacement ``d`` (x, y, z) [m]; the
  viewer draws ``rest + d``. For objects that also move vertices tangentially: the FEM solid
  (:mod:`server.objects.fem`, ``tangential_motion = True``; a bent part swings along an arc
  under modal warping, and a pressed solid's surface slides sideways). It costs three values
  per vertex sent instead of one.

Each value is an ``int16`` count of a quantum (1 um unless the deformation outgrows +-32.767 mm,
see *Scale* below), and a vertex is sent only when the value the viewer holds differs from the
current one by at least a quantum (on some axis, in vector form). At rest the stream costs a
20-byte header per tick; a 10 mm press on a 10k-vertex balloon stays under the per-frame byte
budget (150 kB/s at 20 Hz by default) instead of 2.4 MB/s of float32 positions.

Frames (little-endian; docs/protocol.md, "Viewer stream")
---------------------------------------------------------
On join, three events:

1. ``VTX1`` (:func:`shared.protocol.encode_vertices`, tick 0): the *rest* positions, (n, 3)
   float32 [m];
2. ``NRM1`` (same layout): the rest unit normals, (n, 3) float32 (in vector form the viewer
   still colours the surface by the normal component ``d . rest_normal``);
3. a keyframe (``DSP1`` or ``DSV1``): every vertex's displacement (flags ``DENSE | KEY``).

For a FEM solid with inclusions (``--inclusion``; docs/palpation.md), one ``INC1`` frame per
inclusion follows the keyframe, also as an event (:func:`encode_inclusions`); an object without
inclusions sends none, so its viewers' bytes do not change.

Then one frame of the same form per simulation tick, a latest-wins state stream. Header
(:data:`DSP_HEADER`, 20 bytes, both forms): magic, uint32 tick, uint32 count (vertices), uint32
quantum [nm], uint32 flags. ``DSP1`` body: ``DENSE``: n int16 values (count = n); otherwise
count indices (uint16, or uint32 with ``INDEX32``) then count int16 values. A value ``v`` at
vertex ``i`` means ``w_i = v * quantum``. ``DSV1`` body: the same with three int16 per vertex
(x, y, z, vertex after vertex): ``DENSE``: 3n int16; otherwise count indices then 3 count int16,
``d_i = (vx, vy, vz) * quantum``. Vertices not listed keep what the viewer has.

``INC1`` (:data:`INC_HEADER`, 32 bytes): magic, uint32 index (the inclusion's place in
``--inclusion`` order), uint32 of (how many the object has), uint32 vertices k, uint32 faces m,
float32 Young's modulus ratio (the inclusion's over the solid's; NaN when unknown), uint32
flags (:data:`INC_FLAG_DECIMATED`), uint16 name bytes, uint16 material bytes. Then the name and
the material's name (UTF-8, at most :data:`MAX_INCLUSION_TEXT_BYTES` each; the region's file
name, never a folder), zero-padded to a multiple of 4 bytes; k x 3 float32 rest positions [m] in
the object's frame; m x 3 uint16 vertex indices, counter-clockwise seen from outside. The surface
is the inclusion's at rest: it does not follow the deformation (the FEM tick computes only the
outer surface's displacement). Bounded: at most :data:`MAX_INCLUSIONS_SENT` frames and
:data:`MAX_INCLUSION_FACES` triangles for all of them together, shared out evenly (a small
inclusion keeps all it has and leaves the rest to the others); an inclusion over its share is
decimated by vertex clustering (:func:`server.objects.inclusions.cluster_decimate`) and flagged.

What the server guarantees
--------------------------
The encoder keeps, per viewer, what that viewer holds: the values of the frames the I/O layer
*reported as written* to its socket (:attr:`Frame.sent`), applied in order. A frame the I/O layer
dropped (latest-wins replacement, injected loss) is never reported, so the next frame carries
its vertices again. Values are absolute, not increments, so applying any subset of the frames in
flight leaves the viewer correct: a frame lists every vertex where the viewer's value, or the
value of any frame still in flight, differs from the current one. Hence, with an unlimited
budget, after each frame the viewer holds the server's displacement within half a quantum
(the rounding; per axis in vector form), and the surface it draws is the server's within one
quantum (per axis in vector form).

Byte budget: when more vertices changed than a frame may carry (``frame_budget_bytes``), the
frame carries the largest differences first (flag ``PARTIAL``; in vector form a vertex's
difference is the Euclidean norm of its per-axis differences); the rest follow in the next
frames, so during fast motion small far-field changes lag by a few ticks (under 0.5 mm in
``haptic bench server``) and everything is exact again within a few ticks of the motion stopping.

Scale: if ``max |w|`` (in vector form, the largest ``|d|`` on any axis) exceeds what int16 holds
at the base quantum, the quantum doubles (up to 2**15 base quanta, +-1 km); it halves again once
the deformation fits in half of the smaller range (hysteresis). Values beyond even that are
clamped and flagged ``CLAMPED``.

Pure numpy; no sockets, no clocks. The I/O layer must deliver a viewer's frames in the order they
were made (dropping some is fine) and call :attr:`Frame.sent` right after writing one.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from haptic_collab.shared.protocol import BINARY_HEADER, encode_vertices
from haptic_collab.shared.types import FloatArray

if TYPE_CHECKING:
    from haptic_collab.server.objects.inclusions import InclusionSurface

Int16Array = npt.NDArray[np.int16]
Int32Array = npt.NDArray[np.int32]
Int64Array = npt.NDArray[np.int64]

#: Normal displacement frame: header :data:`DSP_HEADER`, then indices and/or int16 values.
DISPLACEMENT_MAGIC = b"DSP1"
#: Vector displacement frame: header :data:`DSP_HEADER`, then indices and/or int16 (x, y, z).
VECTOR_MAGIC = b"DSV1"
#: Rest normals: header :data:`shared.protocol.BINARY_HEADER`, then count x 3 float32.
NORMALS_MAGIC = b"NRM1"
#: ``DSP1``/``DSV1`` header: magic, uint32 tick, uint32 count, uint32 quantum [nm], uint32 flags.
DSP_HEADER = struct.Struct("<4sIIII")

#: Body is one value (``DSP1``) or three (``DSV1``) per vertex, in vertex order (no indices).
FLAG_DENSE = 1
#: Keyframe: every vertex is listed; the viewer's earlier state no longer matters.
FLAG_KEY = 2
#: Indices are uint32 (meshes of more than 65 536 vertices); uint16 otherwise.
FLAG_INDEX32 = 4
#: Some displacement exceeded 32767 quanta at the largest scale and was clamped.
FLAG_CLAMPED = 8
#: The byte budget cut this frame short: more changes follow in the next frames.
FLAG_PARTIAL = 16

#: An inclusion's rest surface (FEM solid with ``--inclusion``): header :data:`INC_HEADER`, the
#: name and material (UTF-8, padded to 4 bytes), k x 3 float32 [m], m x 3 uint16.
INCLUSION_MAGIC = b"INC1"
#: ``INC1`` header: magic, uint32 index, uint32 of, uint32 vertices, uint32 faces, float32
#: Young's modulus ratio, uint32 flags, uint16 name bytes, uint16 material bytes.
INC_HEADER = struct.Struct("<4sIIIIfIHH")
#: The surface was decimated to fit :data:`MAX_INCLUSION_FACES`.
INC_FLAG_DECIMATED = 1
#: At most this many ``INC1`` frames a viewer gets (the first inclusions, in ``--inclusion`` order).
MAX_INCLUSIONS_SENT = 16
#: At most this many triangles in all ``INC1`` frames together: with their vertices about
#: 50 kB for closed surfaces, 170 kB at worst (a lump's shape is clear in a few hundred).
MAX_INCLUSION_FACES = 4096
#: At most this many vertices in one ``INC1`` frame (every triangle its own three corners).
MAX_INCLUSION_VERTICES = 3 * MAX_INCLUSION_FACES
#: At most this many bytes of UTF-8 for a name or a material's name (cut at a character).
MAX_INCLUSION_TEXT_BYTES = 64

#: Smallest quantum [nm] (1 um).
BASE_QUANTUM_NM = 1000
#: Largest quantum is ``BASE_QUANTUM_NM * 2**MAX_SCALE_EXP`` (32.8 mm; range +-1.07 km).
MAX_SCALE_EXP = 15
#: Default viewer budget [bytes/s]; divided by the simulation rate for the per-frame budget.
DEFAULT_BYTES_PER_S = 150_000
#: No per-frame budget goes below this [bytes] (a very high simulation rate would starve it).
MIN_FRAME_BUDGET_BYTES = 1024

_INT16_MAX = 32767
#: What the encoder knows the viewer holds when it does not know (it is never a valid value).
_UNKNOWN = np.iinfo(np.int32).min


def vertex_normals(vertices: npt.ArrayLike, faces: npt.ArrayLike) -> FloatArray:
    """Area-weighted outward unit vertex normals.

    Parameters
    ----------
    vertices : (n, 3) float [m]
    faces : (m, 3) int
        Counter-clockwise seen from outside.

    Returns
    -------
    (n, 3) float64
        Unit normals; (0, 0, 1) for a vertex that no face uses.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    out = np.divide(vn, length, out=np.zeros_like(vn), where=length > 0)
    out[length[:, 0] == 0] = (0.0, 0.0, 1.0)
    return out


@dataclass(frozen=True, eq=False)
class Snapshot:
    """One tick's quantised displacement, computed once and shared by every viewer.

    Attributes
    ----------
    tick : int
        Simulation tick number.
    scale_exp : int
        The quantum is ``BASE_QUANTUM_NM * 2**scale_exp`` [nm].
    values : (n,) or (n, 3) int16
        ``w`` (normal form) or ``d`` (vector form) in quanta.
    target : (n,) or (n, 3) int32
        ``values * 2**scale_exp``: the same in base quanta (1 um), as a viewer decodes it.
    clamped : bool
        Some ``|w|`` (or component of ``d``) exceeded the int16 range at the largest scale.
    version : int
        Counts the distinct displacements of one stream (frames made from one snapshot for
        viewers in the same state are encoded once).
    """

    tick: int
    scale_exp: int
    values: Int16Array
    target: Int32Array
    clamped: bool
    version: int = 0

    @property
    def quantum_nm(self) -> int:
        """Quantum of :attr:`values` [nm]."""
        return BASE_QUANTUM_NM << self.scale_exp

    @property
    def quantum_m(self) -> float:
        """Quantum of :attr:`values` [m]."""
        return self.quantum_nm * 1e-9


@dataclass(frozen=True, eq=False)
class Frame:
    """One ``DSP1`` (normal form) or ``DSV1`` (vector form) frame for one viewer.

    Attributes
    ----------
    data : bytes
        The binary websocket frame.
    sent : callable
        Call it (no arguments) right after ``data`` is written to that viewer's socket; never for
        a frame that was dropped. The encoder counts on it to know what the viewer holds.
    count : int
        Vertices carried.
    dense, partial : bool
        Flags ``DENSE`` and ``PARTIAL`` (the byte budget held changes back).
    """

    data: bytes
    sent: Callable[[], None] = field(repr=False)
    count: int = 0
    dense: bool = False
    partial: bool = False


@dataclass(frozen=True, eq=False)
class _Encoded:
    """A frame's content, shared by the viewers that held the same state (read-only arrays)."""

    index: Int64Array | None  # None: dense, every vertex
    target: Int32Array  # base quanta sent, as many rows as index (or n); (k,) or (k, 3)
    data: bytes
    partial: bool
    #: Token of the exact state a viewer is in once it got this frame and nothing else is in
    #: flight: the snapshot's version when complete; for a partial frame shared by viewers in one
    #: state a fresh negative number; None when not known exactly.
    result: int | None


@dataclass(frozen=True, eq=False)
class _InFlight:
    """A frame made but not yet reported written."""

    seq: int
    content: _Encoded


@dataclass(eq=False)
class _Viewer:
    """What the encoder knows of one viewer."""

    held: Int32Array  # (n,) or (n, 3) base quanta it holds for sure; _UNKNOWN where unknown
    in_flight: deque[_InFlight] = field(default_factory=deque)
    next_seq: int = 1
    last_sent_seq: int = 0
    #: Token of the exact state the viewer is in, with nothing in flight (else None): the
    #: version of a snapshot whose target it holds, or the token of a shared partial frame.
    synced: int | None = None


class ViewerStream:
    """Encoder of the viewer stream for one object; keeps per-viewer state of what was sent.

    Parameters
    ----------
    rest_vertices : (n, 3) float [m]
        Rest positions.
    rest_normals : (n, 3) float
        Outward unit normals at rest; the normal form measures the displacement along them.
    frame_budget_bytes : int or None
        Largest frame after the keyframe [bytes] (None: unlimited, every frame exact).
    max_in_flight : int
        Frames per viewer tracked while not yet reported written; older ones are forgotten and
        their vertices resent (a viewer too slow to take frames costs a few more bytes, never
        unbounded memory).
    vector : bool
        False: the normal form (``DSP1``, one value per vertex, ``w`` along the rest normal);
        True: the vector form (``DSV1``, the full displacement ``d``, three values per vertex),
        for objects that move vertices off their normals (module docstring).
    inclusions : sequence of server.objects.inclusions.InclusionSurface
        The object's inclusions at rest, sent to each viewer on join as ``INC1`` frames
        (:func:`encode_inclusions`, bounded); none by default.

    Raises
    ------
    ValueError
        Shapes that do not match, an empty mesh, a non-finite rest state, a budget below a
        header and two entries, or ``max_in_flight < 1``.
    """

    def __init__(
        self,
        rest_vertices: npt.ArrayLike,
        rest_normals: npt.ArrayLike,
        frame_budget_bytes: int | None = None,
        max_in_flight: int = 8,
        vector: bool = False,
        inclusions: Sequence[InclusionSurface] = (),
    ) -> None:
        rest = np.array(rest_vertices, dtype=np.float64)
        normals = np.array(rest_normals, dtype=np.float64)
        if rest.ndim != 2 or rest.shape[1] != 3 or rest.shape[0] == 0:
            raise ValueError(f"rest_vertices must be (n, 3) with n > 0, got {rest.shape}")
        if normals.shape != rest.shape:
            raise ValueError(f"rest_normals must be {rest.shape}, got {normals.shape}")
        if not (np.all(np.isfinite(rest)) and np.all(np.isfinite(normals))):
            raise ValueError("rest_vertices and rest_normals must be finite")
        #: Values per vertex: 1 (normal form) or 3 (vector form).
        self._axes = 3 if vector else 1
        least = DSP_HEADER.size + 4 * self._axes + 4  # two entries of uint16 index + values
        if frame_budget_bytes is not None and frame_budget_bytes < least:
            raise ValueError(f"frame_budget_bytes must be >= {least}")
        if max_in_flight < 1:
            raise ValueError(f"max_in_flight must be >= 1, got {max_in_flight}")
        rest.setflags(write=False)
        normals.setflags(write=False)
        self._rest = rest
        self._normals = normals
        self.frame_budget_bytes = frame_budget_bytes
        self.max_in_flight = int(max_in_flight)
        n = rest.shape[0]
        self._index_dtype = "<u2" if n <= 0x10000 else "<u4"
        self._index_flag = 0 if n <= 0x10000 else FLAG_INDEX32
        self._magic = VECTOR_MAGIC if vector else DISPLACEMENT_MAGIC
        self._rest_frames = (
            encode_vertices(0, rest),
            BINARY_HEADER.pack(NORMALS_MAGIC, 0, n) + normals.astype("<f4").tobytes(),
        )
        #: The ``INC1`` frames every viewer gets on join (encoded once).
        self.inclusion_frames: tuple[bytes, ...] = tuple(encode_inclusions(inclusions))
        self._scale_exp = 0
        self._version = 0
        self._last_target: Int32Array | None = None
        self._partial_token = 0
        self._viewers: dict[str, _Viewer] = {}
        #: Frames of the latest snapshot by the version the viewers were synced to.
        self._shared: dict[tuple[int, int], _Encoded] = {}

    @classmethod
    def of_world(
        cls, world: Any, rate_hz: float, bytes_per_s: float | None = DEFAULT_BYTES_PER_S
    ) -> ViewerStream:
        """The stream of a :class:`server.world.World` (or anything with ``vertices`` and ``faces``).

        Rest positions and normals are the object's (``world.obj.rest_vertices`` and
        ``rest_normals``) where it has them, else the current vertices and their area-weighted
        normals (the world is taken to be at rest). The form is the vector form (``DSV1``) when
        the object says its vertices move off their rest normals (a true class attribute
        ``tangential_motion``, as on :class:`server.objects.fem.FemSolid`), else the normal form
        (``DSP1``; the balloon). Either way the stream takes the world's current ``vertices``:
        the vector form carries ``vertices - rest``, the object's (n, 3) displacement.

        An object with per-element materials from inclusions (``obj.materials``, with ``nodes``
        and ``tets``: :class:`server.objects.fem.FemSolid` built with ``--inclusion``) gives the
        stream its inclusions' rest surfaces
        (:func:`server.objects.inclusions.inclusion_surfaces`); any other object none. A solid
        that sags under its own weight (``sag_nodes``, (N, 3) [m], ``--gravity``) has them at
        its sagged rest state: the nodes moved by their linear sag.

        Parameters
        ----------
        world : World
        rate_hz : float
            Frames per second (the simulation rate) [Hz].
        bytes_per_s : float or None
            Budget per viewer [bytes/s]; None for unlimited.
        """
        obj = getattr(world, "obj", None)
        rest = getattr(obj, "rest_vertices", None)
        if rest is None:
            rest = np.asarray(world.vertices, dtype=np.float64)
        normals = getattr(obj, "rest_normals", None)
        if normals is None:
            normals = vertex_normals(rest, world.faces)
        budget = None
        if bytes_per_s is not None:
            budget = max(MIN_FRAME_BUDGET_BYTES, int(bytes_per_s / max(float(rate_hz), 1e-9)))
        vector = getattr(obj, "tangential_motion", False) is True
        inclusions: list[InclusionSurface] = []
        materials = getattr(obj, "materials", None)
        nodes, tets = getattr(obj, "nodes", None), getattr(obj, "tets", None)
        if materials is not None and nodes is not None and tets is not None:
            from haptic_collab.server.objects.inclusions import inclusion_surfaces

            sag = getattr(obj, "sag_nodes", None)  # the rest state under gravity, if any
            if sag is not None and np.shape(sag) == np.shape(nodes):
                nodes = np.asarray(nodes, dtype=np.float64) + np.asarray(sag, dtype=np.float64)
            inclusions = inclusion_surfaces(nodes, tets, materials)
        return cls(rest, normals, frame_budget_bytes=budget, vector=vector, inclusions=inclusions)

    # ------------------------------------------------------------------ state
    @property
    def n_vertices(self) -> int:
        """Number of vertices n."""
        return int(self._rest.shape[0])

    @property
    def rest_vertices(self) -> FloatArray:
        """(n, 3) float64 [m] rest positions (read-only)."""
        return self._rest

    @property
    def rest_normals(self) -> FloatArray:
        """(n, 3) float64 outward unit rest normals (read-only)."""
        return self._normals

    @property
    def vector(self) -> bool:
        """True for the vector form (``DSV1``), False for the normal form (``DSP1``)."""
        return self._axes == 3

    @property
    def viewers(self) -> list[str]:
        """Viewer ids the encoder keeps state for."""
        return list(self._viewers)

    def displacement(self, vertices: npt.ArrayLike) -> FloatArray:
        """What the stream carries of ``vertices``: ``w = (vertices - rest) . rest_normal`` per
        vertex in the normal form, ``d = vertices - rest`` in the vector form.

        Parameters
        ----------
        vertices : (n, 3) float [m]

        Returns
        -------
        (n,) float64 [m] outward positive (normal form), or (n, 3) float64 [m] (vector form);
        non-finite entries become 0.

        Raises
        ------
        ValueError
            ``vertices`` is not (n, 3).
        """
        v = np.asarray(vertices, dtype=np.float64)
        if v.shape != self._rest.shape:
            raise ValueError(f"vertices must be {self._rest.shape}, got {v.shape}")
        d = v - self._rest
        w = d if self._axes == 3 else np.einsum("ij,ij->i", d, self._normals)
        return np.nan_to_num(w, nan=0.0, posinf=0.0, neginf=0.0)

    def snapshot(self, tick: int, vertices: npt.ArrayLike) -> Snapshot:
        """Quantise the current surface once for all viewers (updates the stream's scale).

        Parameters
        ----------
        tick : int
            Simulation tick number (sent modulo 2**32).
        vertices : (n, 3) float [m]
            Current positions.
        """
        base = self.displacement(vertices) * (1e9 / BASE_QUANTUM_NM)  # in base quanta
        peak = float(np.max(np.abs(base))) if base.size else 0.0
        exp = self._scale_exp
        while exp < MAX_SCALE_EXP and peak > (_INT16_MAX << exp):
            exp += 1
        while exp > 0 and peak <= (_INT16_MAX << (exp - 1)) / 2:
            exp -= 1
        self._scale_exp = exp
        scaled = np.rint(base / (1 << exp))
        clamped = bool(np.any(np.abs(scaled) > _INT16_MAX))
        values = np.clip(scaled, -_INT16_MAX, _INT16_MAX).astype(np.int16)
        target = values.astype(np.int32) << exp
        values.setflags(write=False)
        target.setflags(write=False)
        self._shared.clear()
        if self._last_target is None or not np.array_equal(target, self._last_target):
            self._version += 1  # the same displacement keeps its version: viewers stay in step
            self._last_target = target
        return Snapshot(int(tick), exp, values, target, clamped, self._version)

    # ------------------------------------------------------------------ viewers
    def join(self, viewer_id: str, tick: int, vertices: npt.ArrayLike) -> list[bytes]:
        """A new viewer: its keyframe, to be sent as reliable, ordered events.

        Parameters
        ----------
        viewer_id : str
            Connection id; a viewer already known starts over.
        tick : int
            Current tick number.
        vertices : (n, 3) float [m]
            Current positions.

        Returns
        -------
        list of bytes
            ``[VTX1 rest positions, NRM1 rest normals, keyframe]`` (a ``DSP1`` or ``DSV1``
            keyframe, the stream's form), then the ``INC1`` frames of the object's inclusions
            (none without). The keyframe counts as held by the viewer from now on: events are
            never dropped.
        """
        snap = self.snapshot(tick, vertices)
        self._viewers[viewer_id] = _Viewer(held=snap.target.copy(), synced=snap.version)
        key = self._encode(snap, None, FLAG_DENSE | FLAG_KEY)
        return [*self._rest_frames, key, *self.inclusion_frames]

    def leave(self, viewer_id: str) -> None:
        """Forget a viewer (no error if unknown)."""
        self._viewers.pop(viewer_id, None)

    def frames(
        self, tick: int, vertices: npt.ArrayLike, viewer_ids: Iterable[str]
    ) -> dict[str, Frame]:
        """This tick's frame for each viewer; viewers not listed are forgotten.

        Parameters
        ----------
        tick : int
            Simulation tick number.
        vertices : (n, 3) float [m]
            Current positions.
        viewer_ids : iterable of str
            The viewers connected now.

        Returns
        -------
        dict viewer id -> Frame
            A viewer that never joined gets every vertex (in one dense frame, or over several
            under the budget); it has no rest geometry, though: call :meth:`join` first.
        """
        ids = list(viewer_ids)
        keep = set(ids)
        for gone in [v for v in self._viewers if v not in keep]:
            del self._viewers[gone]
        if not ids:
            return {}
        snap = self.snapshot(tick, vertices)
        return {v: self.frame(v, snap) for v in ids}

    def frame(self, viewer_id: str, snap: Snapshot) -> Frame:
        """The frame that brings ``viewer_id`` to ``snap`` (within the byte budget).

        Parameters
        ----------
        viewer_id : str
        snap : Snapshot
            From :meth:`snapshot` of this stream.

        Returns
        -------
        Frame
            Its :attr:`Frame.sent` must be called once the frame is written to the socket.
        """
        state = self._viewers.get(viewer_id)
        if state is None:
            state = self._viewers[viewer_id] = _Viewer(
                held=np.full(snap.target.shape, _UNKNOWN, dtype=np.int32)
            )
        if state.synced is None:
            content = self._content(state, snap, shared=False)
        else:  # viewers in the same state get the same frame: encode it once
            key = (state.synced, snap.version)
            found = self._shared.get(key)
            content = found or self._shared.setdefault(key, self._content(state, snap, shared=True))
        seq = state.next_seq
        state.next_seq += 1
        state.synced = None
        state.in_flight.append(_InFlight(seq, content))
        while len(state.in_flight) > self.max_in_flight:
            old = state.in_flight.popleft().content  # forget it: its vertices count as unknown
            if old.index is None:
                state.held[:] = _UNKNOWN
            else:
                state.held[old.index] = _UNKNOWN
        return Frame(
            data=content.data,
            sent=partial(_mark_sent, state, seq),
            count=self.n_vertices if content.index is None else int(content.index.size),
            dense=content.index is None,
            partial=content.partial,
        )

    def _content(self, state: _Viewer, snap: Snapshot, shared: bool) -> _Encoded:
        """Choose and encode the vertices ``state`` needs to reach ``snap`` (budget permitting).

        ``shared``: ``state`` is exact (``synced``), so a partial frame leads to an exact state
        that other viewers taking the same frame share.
        """
        target = snap.target
        diff = _difference(target, state.held)
        for e in state.in_flight:  # a frame in flight may yet land: its values must be overwritten
            c = e.content
            if c.index is None:
                np.maximum(diff, _difference(target, c.target), out=diff)
            else:
                d = _difference(target[c.index], c.target)
                diff[c.index] = np.maximum(diff[c.index], d)
        changed = np.flatnonzero(diff)
        values_size = 2 * self._axes  # int16 per vertex
        dense_size = values_size * self.n_vertices
        entry = np.dtype(self._index_dtype).itemsize + values_size
        budget = self.frame_budget_bytes
        room = None if budget is None else budget - DSP_HEADER.size
        dense_fits = room is None or dense_size <= room
        flags = 0
        index: Int64Array | None
        if dense_fits and dense_size <= entry * changed.size:
            index, flags = None, FLAG_DENSE
        elif room is not None and entry * changed.size > room:
            cap = room // entry
            index = np.sort(changed[np.argpartition(diff[changed], changed.size - cap)[-cap:]])
            flags = FLAG_PARTIAL
        else:
            index = changed
        sent = target if index is None else target[index]
        if index is not None:
            index.setflags(write=False)
            sent.setflags(write=False)
        data = self._encode(snap, index, flags)
        result: int | None = snap.version
        if flags & FLAG_PARTIAL:
            self._partial_token -= 1
            result = self._partial_token if shared else None
        return _Encoded(index, sent, data, bool(flags & FLAG_PARTIAL), result)

    def _encode(self, snap: Snapshot, index: Int64Array | None, flags: int) -> bytes:
        if snap.clamped:
            flags |= FLAG_CLAMPED
        if index is None:
            count = self.n_vertices
            body = snap.values.astype("<i2").tobytes()
        else:
            flags |= self._index_flag
            count = int(index.size)
            body = index.astype(self._index_dtype).tobytes()
            body += snap.values[index].astype("<i2").tobytes()
        head = DSP_HEADER.pack(self._magic, snap.tick & 0xFFFFFFFF, count, snap.quantum_nm, flags)
        return head + body


def _text(value: str) -> bytes:
    """``value`` as UTF-8, cut to :data:`MAX_INCLUSION_TEXT_BYTES` at a character boundary."""
    data = str(value).encode("utf-8", "replace")[:MAX_INCLUSION_TEXT_BYTES]
    return data.decode("utf-8", "ignore").encode("utf-8")


def _shares(faces: Sequence[int], total: int) -> list[int]:
    """Triangles each inclusion may keep: ``total`` shared out evenly, smallest first, each
    taking what it has up to an even share of what is left (the sum is at most ``total``)."""
    out = [0] * len(faces)
    left = total
    order = sorted(range(len(faces)), key=lambda i: faces[i])
    for done, i in enumerate(order):
        out[i] = min(int(faces[i]), left // (len(faces) - done))
        left -= out[i]
    return out


def encode_inclusions(
    inclusions: Sequence[InclusionSurface],
    max_faces: int = MAX_INCLUSION_FACES,
    max_count: int = MAX_INCLUSIONS_SENT,
) -> list[bytes]:
    """The ``INC1`` frames of an object's inclusions (module docstring: the format).

    Bounded so that no inclusion mesh, however large, floods a viewer: the first ``max_count``
    inclusions only, and ``max_faces`` triangles for all of them together, shared out evenly
    (:func:`_shares`); an inclusion over its share is decimated by vertex clustering
    (:func:`server.objects.inclusions.cluster_decimate`, flag :data:`INC_FLAG_DECIMATED`).
    Unused vertices are dropped. An inclusion with a non-finite vertex, an index out of range or
    no triangle left is not sent (the others keep their ``index``).

    Parameters
    ----------
    inclusions : sequence of InclusionSurface
        ``vertices`` (k, 3) [m], ``faces`` (m, 3), ``name``, ``material``, ``young_ratio``.
    max_faces : int
        Triangles in all frames together (<= :data:`MAX_INCLUSION_FACES`: the viewer refuses
        more).
    max_count : int
        Frames at most (<= :data:`MAX_INCLUSIONS_SENT`).

    Returns
    -------
    list of bytes
        One ``INC1`` frame per inclusion sent; empty for no inclusions.
    """
    items = list(inclusions)
    if not items:
        return []
    sent = items[: max(0, min(int(max_count), MAX_INCLUSIONS_SENT))]
    geometry: list[tuple[FloatArray, npt.NDArray[np.int64]] | None] = []
    for inc in sent:
        v = np.asarray(inc.vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(inc.faces, dtype=np.int64).reshape(-1, 3)
        ok = len(f) > 0 and bool(np.all(np.isfinite(v)))
        ok = ok and int(f.min()) >= 0 and int(f.max()) < len(v)
        geometry.append((v, f) if ok else None)
    counts = [0 if g is None else len(g[1]) for g in geometry]
    shares = _shares(counts, min(int(max_faces), MAX_INCLUSION_FACES))
    out = []
    for index, (inc, g, share) in enumerate(zip(sent, geometry, shares, strict=True)):
        if g is None:
            continue
        v, f = g
        flags = 0
        if len(f) > share:
            from haptic_collab.server.objects.inclusions import cluster_decimate

            v, f, _ = cluster_decimate(v, f, share)
            flags |= INC_FLAG_DECIMATED
        if len(f) == 0:
            continue
        used, renumbered = np.unique(f, return_inverse=True)
        v, f = v[used], renumbered.reshape(-1, 3)
        name, material = _text(inc.name), _text(inc.material)
        ratio = float(inc.young_ratio)
        head = INC_HEADER.pack(
            INCLUSION_MAGIC,
            index,
            len(items),
            len(v),
            len(f),
            ratio if math.isfinite(ratio) and abs(ratio) < 3e38 else math.nan,  # float32
            flags,
            len(name),
            len(material),
        )
        text = name + material
        text += b"\0" * (-len(text) % 4)
        out.append(head + text + v.astype("<f4").tobytes() + f.astype("<u2").tobytes())
    return out


def _difference(a: Int32Array, b: Int32Array) -> npt.NDArray[Any]:
    """Per vertex, how far apart two sets of values [base quanta] are.

    (n,) values (normal form): ``|a - b|``, int64. (n, 3) values (vector form): the Euclidean
    norm of the row differences, float64 (exactly 0 only where the rows are equal).
    """
    d = a.astype(np.int64) - b
    if d.ndim == 1:
        return np.abs(d)
    return np.sqrt(np.einsum("ij,ij->i", d, d, dtype=np.float64))


def _mark_sent(state: _Viewer, seq: int) -> None:
    """Frame ``seq`` reached the viewer's socket: the viewer now holds its values.

    Frames older than ``seq`` still in flight were dropped (frames go out in order), so they are
    forgotten. A report out of order breaks that rule: the encoder then trusts nothing it knew.
    """
    state.synced = None
    if seq <= state.last_sent_seq:
        state.held[:] = _UNKNOWN
        state.in_flight.clear()
        return
    state.last_sent_seq = seq
    while state.in_flight and state.in_flight[0].seq <= seq:
        e = state.in_flight.popleft()
        if e.seq != seq:
            continue
        c = e.content
        if c.index is None:
            state.held[:] = c.target
        else:
            state.held[c.index] = c.target
        if not state.in_flight:
            state.synced = c.result  # the exact state the viewer is in (None: not known)
