"""The viewer's side of the viewer stream: decoding its frames and applying them to the surface.

:mod:`server.viewer_stream` encodes the deforming surface for the viewers (its docstring has the
wire format: ``VTX1`` rest positions, ``NRM1`` rest normals, then ``DSP1`` normal or ``DSV1``
vector displacements). This module is what a viewer does with those frames, in Python: it is the
reference web/viewer.js follows, and what the tests and ``haptic bench server`` check the stream
against. :func:`decode_displacement` reads one ``DSP1``/``DSV1`` frame; a
:class:`ViewerStreamDecoder` fed every frame in the order received holds the surface the viewer
draws. :func:`decode_inclusion` reads and checks an ``INC1`` frame (an inclusion's rest
surface), as web/lump.js does in the browser.

Pure numpy; no sockets, no clocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from haptic_collab.server.viewer_stream import (
    DISPLACEMENT_MAGIC,
    DSP_HEADER,
    FLAG_DENSE,
    FLAG_INDEX32,
    INC_FLAG_DECIMATED,
    INC_HEADER,
    INCLUSION_MAGIC,
    MAX_INCLUSION_FACES,
    MAX_INCLUSION_TEXT_BYTES,
    MAX_INCLUSION_VERTICES,
    MAX_INCLUSIONS_SENT,
    NORMALS_MAGIC,
    VECTOR_MAGIC,
    Int16Array,
    Int64Array,
)
from haptic_collab.shared.protocol import BINARY_HEADER, VERTICES_MAGIC
from haptic_collab.shared.types import FloatArray


@dataclass(frozen=True, eq=False)
class DisplacementFrame:
    """A decoded ``DSP1`` or ``DSV1`` frame.

    Attributes
    ----------
    tick : int
    quantum_m : float
        Quantum of :attr:`values` [m].
    flags : int
        ``FLAG_*`` bits.
    index : (count,) int64 or None
        Vertices carried (None: dense, all of them in order).
    values : (count,) or (count, 3) int16
        Displacements in quanta: ``w`` along the rest normal (``DSP1``), or ``d`` (x, y, z)
        (``DSV1``).
    """

    tick: int
    quantum_m: float
    flags: int
    index: Int64Array | None
    values: Int16Array

    @property
    def vector(self) -> bool:
        """True for a ``DSV1`` frame (three values per vertex)."""
        return self.values.ndim == 2


def decode_displacement(frame: bytes) -> DisplacementFrame:
    """Decode a ``DSP1`` or ``DSV1`` frame (no mesh needed; :class:`ViewerStreamDecoder`
    applies it).

    Raises
    ------
    ValueError
        Neither a ``DSP1`` nor a ``DSV1`` frame, or a length that does not match its header.
    """
    if len(frame) < DSP_HEADER.size:
        raise ValueError("displacement frame shorter than its header")
    magic, tick, count, quantum_nm, flags = DSP_HEADER.unpack_from(frame)
    if magic not in (DISPLACEMENT_MAGIC, VECTOR_MAGIC):
        raise ValueError(f"not a DSP1 or DSV1 frame: {magic!r}")
    name = magic.decode()
    axes = 3 if magic == VECTOR_MAGIC else 1
    shape = (count, 3) if axes == 3 else (count,)
    body = memoryview(frame)[DSP_HEADER.size :]
    if flags & FLAG_DENSE:
        if len(body) != 2 * axes * count:
            raise ValueError(f"{name} dense frame length does not match its count")
        values = np.frombuffer(body, dtype="<i2").astype(np.int16).reshape(shape)
        return DisplacementFrame(tick, quantum_nm * 1e-9, flags, None, values)
    width = 4 if flags & FLAG_INDEX32 else 2
    if len(body) != (width + 2 * axes) * count:
        raise ValueError(f"{name} sparse frame length does not match its count")
    index = np.frombuffer(body[: width * count], dtype="<u4" if width == 4 else "<u2")
    values = np.frombuffer(body[width * count :], dtype="<i2").astype(np.int16).reshape(shape)
    return DisplacementFrame(tick, quantum_nm * 1e-9, flags, index.astype(np.int64), values)


#: Largest |coordinate| [m] of an inclusion's vertex a viewer accepts (web/lump.js: the same).
MAX_INCLUSION_COORD_M = 1000.0


@dataclass(frozen=True, eq=False)
class DecodedInclusion:
    """A decoded ``INC1`` frame: one inclusion's rest surface.

    Attributes
    ----------
    index, of : int
        Its place in the object's inclusions, and how many the object has.
    name, material : str
        Its region (file name) and its material's name.
    young_ratio : float or None
        Its Young's modulus over the solid's [1]; None when the server did not know it.
    decimated : bool
        The server simplified it to fit its triangle budget.
    vertices : (k, 3) float64 [m]
    faces : (m, 3) int64
    """

    index: int
    of: int
    name: str
    material: str
    young_ratio: float | None
    decimated: bool
    vertices: FloatArray
    faces: Int64Array


def decode_inclusion(frame: bytes) -> DecodedInclusion:
    """Decode and check an ``INC1`` frame (server/viewer_stream.py has the format).

    Refused, as web/lump.js refuses them: a frame shorter than its header or of another length
    than its counts say; more vertices or triangles than one frame may hold, an index beyond
    :data:`server.viewer_stream.MAX_INCLUSIONS_SENT` or not below ``of``; a text longer than
    :data:`server.viewer_stream.MAX_INCLUSION_TEXT_BYTES`; a vertex that is not finite or beyond
    :data:`MAX_INCLUSION_COORD_M`; a triangle index out of range.

    Raises
    ------
    ValueError
        Says which check failed.
    """
    if len(frame) < INC_HEADER.size:
        raise ValueError("INC1 frame shorter than its header")
    magic, index, of, k, m, ratio, flags, nb, mb = INC_HEADER.unpack_from(frame)
    if magic != INCLUSION_MAGIC:
        raise ValueError(f"not an INC1 frame: {magic!r}")
    if not (index < of and index < MAX_INCLUSIONS_SENT):
        raise ValueError(f"INC1 index {index} of {of} out of range")
    if not (3 <= k <= MAX_INCLUSION_VERTICES and 1 <= m <= MAX_INCLUSION_FACES):
        raise ValueError(f"INC1 with {k} vertices and {m} triangles: out of bounds")
    if nb > MAX_INCLUSION_TEXT_BYTES or mb > MAX_INCLUSION_TEXT_BYTES:
        raise ValueError("INC1 name or material too long")
    text = nb + mb + (-(nb + mb) % 4)
    start = INC_HEADER.size + text
    if len(frame) != start + 12 * k + 6 * m:
        raise ValueError("INC1 frame length does not match its counts")
    raw = bytes(frame[INC_HEADER.size : INC_HEADER.size + nb + mb])
    v = np.frombuffer(frame, dtype="<f4", count=3 * k, offset=start).reshape(k, 3)
    f = np.frombuffer(frame, dtype="<u2", count=3 * m, offset=start + 12 * k).reshape(m, 3)
    if not (np.all(np.isfinite(v)) and np.all(np.abs(v) <= MAX_INCLUSION_COORD_M)):
        raise ValueError("INC1 vertex not finite or out of range")
    if int(f.max()) >= k:
        raise ValueError("INC1 triangle index out of range")
    return DecodedInclusion(
        index=index,
        of=of,
        name=raw[:nb].decode("utf-8", "replace"),
        material=raw[nb:].decode("utf-8", "replace"),
        young_ratio=float(ratio) if np.isfinite(ratio) and ratio > 0 else None,
        decimated=bool(flags & INC_FLAG_DECIMATED),
        vertices=v.astype(np.float64),
        faces=f.astype(np.int64),
    )


class ViewerStreamDecoder:
    """What a viewer does with the stream (the reference for web/viewer.js).

    Feed it every binary frame in the order received; :attr:`vertices` is then the surface. A
    ``DSP1`` frame sets normal displacements ``w`` (drawn ``rest + w * normal``); a ``DSV1``
    frame sets vector displacements ``d`` (drawn ``rest + d``), and ``w`` follows as their
    normal component. A stream keeps one form; a frame of the other form switches to it (a
    ``DSP1`` frame drops the vectors, the vertices it does not list keep their ``w``).
    """

    def __init__(self) -> None:
        self.rest: FloatArray | None = None
        self.normals: FloatArray | None = None
        self._w: FloatArray | None = None
        #: (n, 3) [m] vector displacements once a ``DSV1`` frame came; None in the normal form.
        self._d: FloatArray | None = None
        self.tick = -1
        self.frames = 0
        #: The inclusions received (``INC1``), by index; a ``VTX1`` frame (a new join) clears
        #: them.
        self.inclusions: dict[int, DecodedInclusion] = {}

    @property
    def w(self) -> FloatArray:
        """(n,) float64 [m] the normal displacement the viewer holds, outward positive (in the
        vector form, the normal component of :attr:`displacement`).

        Raises
        ------
        ValueError
            Before the rest geometry arrived.
        """
        if self._w is None:
            raise ValueError("no rest geometry yet")
        if self._d is not None:
            if self.normals is None:
                raise ValueError("no rest normals yet")
            return np.einsum("ij,ij->i", self._d, self.normals)
        return self._w

    @property
    def vector(self) -> bool:
        """True once the stream is in the vector form (the last displacement frame was DSV1)."""
        return self._d is not None

    def feed(self, frame: bytes) -> None:
        """Apply one binary frame (``VTX1`` rest, ``NRM1``, ``DSP1``, ``DSV1``, ``INC1``;
        others are ignored).

        Raises
        ------
        ValueError
            A malformed frame, or a displacement frame before the rest geometry or of another
            size.
        """
        magic = bytes(frame[:4])
        if magic in (DISPLACEMENT_MAGIC, VECTOR_MAGIC):
            d = decode_displacement(frame)
            name = magic.decode()
            if self._w is None:
                raise ValueError(f"{name} frame before the rest geometry (VTX1, NRM1)")
            n = self._w.size
            if d.index is None and d.values.shape[0] != n:
                raise ValueError(f"{name} dense frame of another mesh size")
            if d.index is not None and d.index.size and int(d.index.max()) >= n:
                raise ValueError(f"{name} index out of range")
            rows = slice(None) if d.index is None else d.index
            if d.vector:
                if self._d is None:
                    self._d = np.zeros((n, 3))
                self._d[rows] = d.values * d.quantum_m
            else:
                if self._d is not None:  # back to the normal form: keep the normal component
                    self._w = self.w
                    self._d = None
                self._w[rows] = d.values * d.quantum_m
            self.tick = d.tick
            self.frames += 1
        elif magic in (VERTICES_MAGIC, NORMALS_MAGIC):
            _, _, count = BINARY_HEADER.unpack_from(frame)
            body = memoryview(frame)[BINARY_HEADER.size :]
            if len(body) != 12 * count:
                raise ValueError(f"{magic!r} frame length does not match its count")
            arr = np.frombuffer(body, dtype="<f4").reshape(count, 3).astype(np.float64)
            if magic == VERTICES_MAGIC:
                self.rest, self._w, self._d = arr, np.zeros(count), None
                self.inclusions = {}
            else:
                self.normals = arr
        elif magic == INCLUSION_MAGIC:
            inc = decode_inclusion(frame)
            self.inclusions[inc.index] = inc

    @property
    def displacement(self) -> FloatArray:
        """(n, 3) float64 [m] the displacement the viewer draws: ``d`` (vector form) or
        ``w * normal`` (normal form).

        Raises
        ------
        ValueError
            Before the rest geometry arrived.
        """
        if self.normals is None or self._w is None:
            raise ValueError("no rest geometry yet")
        if self._d is not None:
            return self._d.copy()
        return self._w[:, None] * self.normals

    @property
    def vertices(self) -> FloatArray:
        """(n, 3) float64 [m] the surface as the viewer draws it, ``rest + w * normal`` (normal
        form) or ``rest + d`` (vector form).

        Raises
        ------
        ValueError
            Before the rest geometry arrived.
        """
        if self.rest is None:
            raise ValueError("no rest geometry yet")
        return self.rest + self.displacement
