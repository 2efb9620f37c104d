"""Wire protocol between the server, the haptic clients and the browser viewers (version 1).

JSON text frames carry one message each, a pydantic model discriminated by ``type``; every message
a client sends first is ``hello`` with the protocol version. Surface geometry goes to viewers as
binary frames (:func:`encode_vertices`, :func:`encode_faces`). docs/protocol.md describes it all with
a complete example exchange; ``haptic protocol --schema`` prints the JSON Schema.

Streams and events (viser's rule): ``state`` (client -> server), ``patch`` and ``room``
(server -> client) are *latest wins* state streams — a newer one replaces any queued older one;
``hello``, ``welcome``, ``error``, ``bye`` are events, delivered reliably and in order.

Only the network edge uses pydantic; the servo tick never sees these classes. All quantities SI:
positions [m], forces [N], stiffness [N/m], I [N/(m*s)], rates [Hz], times [s] unless a field name
says ``_ms`` or ``_us``.
"""

from __future__ import annotations

import json
import struct
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, Strict, TypeAdapter, ValidationError

PROTOCOL_VERSION = 1

#: Largest text or binary frame a client may send [bytes]; the server closes on larger ones.
MAX_CLIENT_FRAME_BYTES = 16 * 1024
#: Largest force a client may report [N]; larger reports are rejected (no device exceeds this).
MAX_REPORTED_FORCE_N = 50.0
#: Largest probe distance from the origin a client may report [m].
MAX_PROBE_DISTANCE_M = 100.0
#: Sequence numbers and ping ids stay below this (the largest integer a JavaScript number holds).
MAX_SEQ = 2**53
#: Containers (``[`` plus ``{``) and commas a client frame may hold, counted before parsing: a
#: valid message has fewer than 10 and 40; the cap bounds nesting depth and array lengths.
MAX_FRAME_CONTAINERS = 64
MAX_FRAME_COMMAS = 512
#: Longest resume token [characters] a ``hello`` may carry (the server's are 32: 24 random bytes
#: in URL-safe base64, :func:`server.security.new_resume_token`).
MAX_RESUME_TOKEN_CHARS = 128

Role = Literal["user", "viewer"]


class _Msg(BaseModel):
    model_config = ConfigDict(extra="ignore", allow_inf_nan=False, frozen=True)


Finite = Annotated[float, Field(allow_inf_nan=False)]
FiniteVec3 = tuple[Finite, Finite, Finite]
Name = Annotated[str, Field(min_length=1, max_length=32, pattern=r"^[A-Za-z0-9_.-]+$")]


# Inbound (client -> server) fields are strict: no "1" for 1, no true for 1, no "yes" for true; a
# JSON integer is accepted where a float is expected. Every number has a physical range.
StrictFinite = Annotated[float, Strict(), Field(allow_inf_nan=False)]
StrictBool = Annotated[bool, Strict()]
#: A position component [m]: within 1 km of the origin (the room refuses beyond 100 m).
Coord = Annotated[StrictFinite, Field(ge=-1e3, le=1e3)]
#: A force component [N]: no device comes near; the room applies the much tighter per-user bound.
ForceComponent = Annotated[StrictFinite, Field(ge=-1e6, le=1e6)]
InVec3 = tuple[Coord, Coord, Coord]
ForceVec3 = tuple[ForceComponent, ForceComponent, ForceComponent]
Seq = Annotated[int, Strict(), Field(ge=0, lt=MAX_SEQ)]


# ----------------------------------------------------------------------------- client -> server
class DeviceInfo(_Msg):
    """A user's device, as the server and viewers need to know it."""

    profile: Annotated[str, Strict(), Field(max_length=64)] = "unknown"
    max_force_n: Annotated[StrictFinite, Field(gt=0, le=100)] = 7.9
    max_stiffness_n_per_m: Annotated[StrictFinite, Field(gt=0, le=1e5)] = 1000.0
    #: Largest virtual damping [N*s/m] the device renders stably (the probe damper B_h's limit;
    #: 0: no damper). The server's recommended gains stay within it.
    max_damping_n_s_per_m: Annotated[StrictFinite, Field(ge=0, le=1e3)] = 0.0


class Hello(_Msg):
    """First message of every connection.

    ``token`` authenticates the connection when the server requires tokens (``haptic server
    --token-file`` or ``--token``); browsers cannot set headers on a websocket, so it travels
    here. It is never shown in a ``repr`` or log.

    ``resume`` is the ``resume_token`` of the last ``welcome`` this user got in this room: a
    user whose link dropped gets its seat back (the same ``user_id``, name and contact) when it
    comes back within the server's hold time (30 s; docs/protocol.md, "Rejoin"). A token that
    is wrong, used, expired or another room's is not an error: the user joins as a new one.
    Ignored for viewers; never shown in a ``repr`` or log.
    """

    type: Literal["hello"] = "hello"
    protocol: Annotated[int, Strict(), Field(ge=0, le=2**31)]
    role: Role
    name: Name
    device: DeviceInfo | None = None
    servo_rate_hz: Annotated[StrictFinite, Field(gt=0, le=100_000)] = 1000.0
    local_model: Literal["p", "pi"] = "pi"
    token: Annotated[str, Strict(), Field(min_length=1, max_length=256)] | None = Field(
        default=None, repr=False
    )
    resume: (
        Annotated[str, Strict(), Field(min_length=1, max_length=MAX_RESUME_TOKEN_CHARS)] | None
    ) = Field(default=None, repr=False)


class State(_Msg):
    """A user's latest probe and rendered force, sent once per simulation tick (latest wins).

    ``force_n`` is the last force the device rendered on the user [N] (outward: it pushes the probe
    out of the object); the simulation applies its opposite (Step 3 of section 6).
    ``penetration_m`` is the probe's penetration of its local model [m]; absent (null) before the
    first patch, when there is no local model to penetrate (then ``patch_tick`` is -1).
    """

    type: Literal["state"] = "state"
    seq: Seq
    probe_m: InVec3
    force_n: ForceVec3
    penetration_m: Annotated[StrictFinite, Field(ge=-10.0, le=10.0)] | None = None
    in_contact: StrictBool = False
    k_h: Annotated[StrictFinite, Field(ge=0, le=1e6)] = 0.0
    i_gain: Annotated[StrictFinite, Field(ge=0, le=1e8)] = 0.0
    #: Own-force compensation C_h [m/N] the local model renders with (0: none; 1/K_h: up to
    #: 100 m/N for a K_h of 0.01 N/m).
    own_gain: Annotated[StrictFinite, Field(ge=0, le=100.0)] = 0.0
    servo_rate_hz: Annotated[StrictFinite, Field(ge=0, le=100_000)] = 0.0
    period_us_p99: Annotated[StrictFinite, Field(ge=0, le=1e7)] = 0.0
    rtt_ms: Annotated[StrictFinite, Field(ge=0, le=1e6)] | None = None
    #: The round trip [ms] the client measures its loop delay from (the 90th percentile of its
    #: last 20 round trips, :func:`shared.gains.delay.delay_rtt_s`): the server's gain advisor
    #: designs for the delay of the same round trip (absent: from the reported ``rtt_ms``).
    delay_rtt_ms: Annotated[StrictFinite, Field(ge=0, le=1e6)] | None = None
    patch_tick: Annotated[int, Strict(), Field(ge=-1, lt=MAX_SEQ)] = -1


class Ping(_Msg):
    """Round-trip probe; the server answers with a ``pong`` echoing ``id`` and ``t_client_s``."""

    type: Literal["ping"] = "ping"
    id: Seq
    t_client_s: Annotated[StrictFinite, Field(ge=-1e12, le=1e12)]


class Bye(_Msg):
    """The client is leaving on purpose."""

    type: Literal["bye"] = "bye"


ClientMessage = Annotated[Hello | State | Ping | Bye, Field(discriminator="type")]


# ----------------------------------------------------------------------------- server -> client
class SurfacePoint(_Msg):
    """A point on the object's rest surface [m] and its outward unit normal."""

    point_m: FiniteVec3
    normal: FiniteVec3


class ObjectInfo(_Msg):
    """The shared object, in its rest state: enough for a client to find the top and a side.

    ``sides`` lists side anchors at four azimuths (the vertices furthest along +x, +y, -x, -y),
    those a push on the top moves most first (``server.room.order_sides_by_coupling``), so that
    users resting on a side can spread apart; it may be empty (an older server), then ``side_m``
    (the +x side) is the only side.
    """

    n_vertices: int
    n_faces: int
    center_m: FiniteVec3
    radius_m: Finite
    bounds_min_m: FiniteVec3
    bounds_max_m: FiniteVec3
    top_m: FiniteVec3
    top_normal: FiniteVec3
    side_m: FiniteVec3
    side_normal: FiniteVec3
    sides: list[SurfacePoint] = Field(default_factory=list, max_length=16)


#: Largest injected latency and jitter [ms] (``haptic server --latency-ms``, ``--jitter-ms``).
MAX_LINK_DELAY_MS = 60_000.0
#: An injected delay [ms]: finite, in [0, :data:`MAX_LINK_DELAY_MS`].
LinkDelayMs = Annotated[float, Field(ge=0.0, le=MAX_LINK_DELAY_MS, allow_inf_nan=False)]


class LinkConditions(_Msg):
    """Latency injection in force on each direction of every connection (server.latency).

    ``latency_ms`` [ms] delays every frame; ``jitter_ms`` [ms] adds a delay drawn uniformly from
    ``[-jitter_ms, +jitter_ms]``; both are in [0, 60000]. ``loss`` in [0, 1) is the probability
    that a stream frame (state, patch, room, vertices, ping, pong) is dropped; events never are.
    All zero: no injection.

    Raises
    ------
    pydantic.ValidationError
        (a ValueError) Out of range or non-finite values. :meth:`checked` raises a one-line
        ValueError naming the setting instead, for command-line and configuration input.
    """

    latency_ms: LinkDelayMs = 0.0
    jitter_ms: LinkDelayMs = 0.0
    loss: Annotated[float, Field(ge=0.0, lt=1.0, allow_inf_nan=False)] = 0.0

    @property
    def active(self) -> bool:
        """Whether any impairment is configured."""
        return self.latency_ms > 0.0 or self.jitter_ms > 0.0 or self.loss > 0.0

    @classmethod
    def checked(
        cls, latency_ms: float = 0.0, jitter_ms: float = 0.0, loss: float = 0.0
    ) -> LinkConditions:
        """These conditions, validated with a message a ``haptic server`` user can act on.

        Raises
        ------
        ValueError
            The first setting out of range or non-finite, e.g. ``latency_ms must be in
            [0, 60000] ms, got 70000.0`` or ``loss must be in [0, 1), got 1.0``.
        """
        try:
            return cls(latency_ms=latency_ms, jitter_ms=jitter_ms, loss=loss)
        except ValidationError as exc:
            err = exc.errors()[0]
            name, value = str(err["loc"][0]), err["input"]
        if name == "loss":
            raise ValueError(f"loss must be in [0, 1), got {value!r}") from None
        raise ValueError(
            f"{name} must be in [0, {MAX_LINK_DELAY_MS:g}] ms, got {value!r}"
        ) from None


class Welcome(_Msg):
    """Answer to ``hello``.

    Users get a ``resume_token`` (opaque, unguessable, one use): sent back as ``hello.resume``
    after a dropped link, within the server's hold time, it gives back the same seat
    (``user_id``, name, contact) and that ``welcome`` has ``resumed`` true and a fresh token.
    Viewers get none. Both are absent from an older server's welcome.
    """

    type: Literal["welcome"] = "welcome"
    protocol: int = PROTOCOL_VERSION
    user_id: str
    name: str
    role: Role
    sim_rate_hz: Finite
    object: ObjectInfo
    link: LinkConditions = LinkConditions()
    resume_token: Annotated[str, Field(min_length=1, max_length=MAX_RESUME_TOKEN_CHARS)] | None = (
        Field(default=None, repr=False)
    )
    resumed: bool = False


class PlaneModel(_Msg):
    """Plane primitive: a point on it [m] and its outward unit normal."""

    kind: Literal["plane"] = "plane"
    point: FiniteVec3
    normal: FiniteVec3


class SphereModel(_Msg):
    """Sphere primitive fitted to the local curvature: centre [m] and radius [m]."""

    kind: Literal["sphere"] = "sphere"
    center: FiniteVec3
    radius: Annotated[float, Field(gt=0, allow_inf_nan=False)]


PrimitiveModel = Annotated[PlaneModel | SphereModel, Field(discriminator="kind")]


class RecommendedGains(_Msg):
    """Gains the server recommends for a user's local model (SI units; docs/protocol.md).

    Designed with :func:`shared.gains.design.design_gains` (the Python client's own design) for the
    user's declared device (``max_stiffness_n_per_m``, ``max_damping_n_s_per_m``, servo rate,
    ``local_model``), its reported round trip and the patch's ``k_o_eff``/``k_o_stiff``/``b_o``:
    stable over the hand box at every sampling tick, with the design's margin. ``interim``: these
    are interim gains, only checked stable (a fraction of a second) while the design runs; a
    client with a full design of its own for this contact should prefer its own.
    """

    k_h: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    i_gain: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    b_h: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    proxy_hold: Literal["zoh", "foh"]
    theta_m: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    delay_ticks: Annotated[int, Field(ge=0)]
    interim: bool = False
    #: Own-force compensation C_h [m/N] (shared.full_loop): render against the patch's primitive
    #: moved out by ``own_gain * own_force_n``. 0 (or absent): the paper's local model.
    own_gain: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0


class Patch(_Msg):
    """A user's local model for the next simulation period (latest wins).

    ``k_o`` is the object's local stiffness at the contact, ``k_o_eff`` <= ``k_o`` the
    coupling-aware value (DESIGN section 6) the client must choose its gains below;
    ``k_o_stiff`` >= ``k_o`` the stiffest modal stiffness of the contacts coupled to this one
    (absent or equal to ``k_o``: uncoupled; :meth:`shared.local_model_update.SurfacePatch.from_wire`
    reads an absent one as ``k_o``): a PI local model must be stable for every K_o' in
    ``[k_o_eff, k_o_stiff]`` (docs/coupled-users.md); ``b_o`` the object damping divided by the
    simulation period (eq. 9).
    """

    type: Literal["patch"] = "patch"
    tick: int
    primitive: PrimitiveModel
    proxy_m: FiniteVec3
    normal: FiniteVec3
    penetration_m: Finite
    in_contact: bool
    k_o: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    k_o_eff: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    b_o: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    k_o_stiff: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    #: Force [N] along the normal that the simulation applied from this user in the step that
    #: produced this surface (0: none); with own-force compensation the local model renders
    #: against the primitive moved out by C_h times it.
    own_force_n: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0
    #: Gains the server recommends (absent until designed for this user's key and K_o cell).
    gains: RecommendedGains | None = None
    #: The object's rest surface at this contact (the tangent plane at the contact's material
    #: point), sent only while this user is the only one in the room: a client may
    #: render it with the object's stiffness (:mod:`shared.gains.rest_plane`); absent otherwise.
    rest_plane: PlaneModel | None = None


class Pong(_Msg):
    """Answer to ``ping``."""

    type: Literal["pong"] = "pong"
    id: int
    t_client_s: Finite
    tick: int


class ErrorMsg(_Msg):
    """Something the peer sent was refused. ``fatal`` errors are followed by a close."""

    type: Literal["error"] = "error"
    code: str
    message: str
    fatal: bool = False


class UserView(_Msg):
    """One user as the viewers see it."""

    user_id: str
    name: str
    probe_m: FiniteVec3
    proxy_m: FiniteVec3
    normal: FiniteVec3
    force_n: FiniteVec3
    #: None until the user's client has a local model (its ``state`` says none).
    penetration_m: Finite | None = None
    in_contact: bool
    k_o: Finite
    k_o_eff: Finite
    k_h: Finite
    i_gain: Finite
    servo_rate_hz: Finite
    rtt_ms: Finite | None = None
    device: str = "unknown"


class RoomState(_Msg):
    """What viewers need each tick besides the vertices: users, rates, injected latency."""

    type: Literal["room"] = "room"
    tick: int
    sim_rate_hz: Finite
    tick_ms: Finite
    tick_ms_p99: Finite
    overruns: int
    link: LinkConditions
    users: list[UserView]


ServerMessage = Annotated[
    Welcome | Patch | Pong | ErrorMsg | RoomState, Field(discriminator="type")
]

CLIENT_ADAPTER: TypeAdapter[Hello | State | Ping | Bye] = TypeAdapter(ClientMessage)
SERVER_ADAPTER: TypeAdapter[Welcome | Patch | Pong | ErrorMsg | RoomState] = TypeAdapter(
    ServerMessage
)


class ProtocolError(ValueError):
    """A frame that is not a valid message. ``code`` names the problem for the ``error`` reply."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err.get("loc", ())) or "message"
    return f"{where}: {err.get('msg', 'invalid')}"


_NUMBER_ERRORS = frozenset({"float_type", "int_type", "float_parsing", "int_parsing"})


def frame_size_bytes(frame: str | bytes) -> int:
    """Size of a frame on the wire [bytes]: UTF-8 bytes of a text frame, not characters."""
    if isinstance(frame, str):
        # a character is at most 4 bytes: skip the encoding when even that fits
        return len(frame) if frame.isascii() else len(frame.encode("utf-8", "surrogatepass"))
    return len(frame)


#: Client messages that form a stream (each supersedes the last; a lost one is repaired by the
#: next): loss injection may drop them. Every other message is an event and is never dropped.
CLIENT_STREAM_TYPES = frozenset({"state", "ping"})


def client_stream_frame(frame: str | bytes) -> bool:
    """Whether a client frame is a stream message (:data:`CLIENT_STREAM_TYPES`).

    Reads the frame's ``type`` field only; a frame that is not a JSON object with a string
    ``type`` (binary, malformed, hostile) is not a stream frame: it goes on, undropped, to
    :func:`parse_client`, which refuses it with its own error.
    """
    if not isinstance(frame, str):
        return False
    try:
        check_complexity(frame)
        msg = json.loads(frame)
    except (ValueError, ProtocolError, RecursionError):
        return False
    kind = msg.get("type") if isinstance(msg, dict) else None
    return isinstance(kind, str) and kind in CLIENT_STREAM_TYPES


def check_complexity(text: str) -> None:
    """Bound the cost of parsing a client frame before parsing it.

    Counts containers (``[``, ``{``) and commas with :meth:`str.count` (linear, in C), which bounds
    both the nesting depth and the length of every array; the byte limit
    (:data:`MAX_CLIENT_FRAME_BYTES`) bounds the rest.

    Raises
    ------
    ProtocolError
        ``too_complex`` when the frame holds more than :data:`MAX_FRAME_CONTAINERS` containers or
        :data:`MAX_FRAME_COMMAS` commas.
    """
    containers = text.count("[") + text.count("{")
    if containers > MAX_FRAME_CONTAINERS or text.count(",") > MAX_FRAME_COMMAS:
        raise ProtocolError(
            "too_complex",
            f"a message holds at most {MAX_FRAME_CONTAINERS} arrays or objects and "
            f"{MAX_FRAME_COMMAS} commas",
        )


def _null_number(exc: ValidationError) -> str | None:
    """The location of a JSON ``null`` given where a number was expected, if any."""
    for err in exc.errors():
        if err.get("input", ...) is None and err.get("type") in _NUMBER_ERRORS:
            return ".".join(str(p) for p in err.get("loc", ())) or "message"
    return None


def _parse(adapter: TypeAdapter[Any], text: str | bytes, known: tuple[str, ...]) -> Any:
    if isinstance(text, bytes | bytearray | memoryview):
        raise ProtocolError("binary_not_expected", "expected a JSON text frame")
    try:
        raw = json.loads(text, parse_constant=_reject_constant)
    except ProtocolError:
        raise
    except (ValueError, RecursionError):
        raise ProtocolError("malformed_json", "frame is not valid JSON") from None
    if not isinstance(raw, dict):
        raise ProtocolError("malformed_message", "a message must be a JSON object")
    kind = raw.get("type")
    if kind not in known:
        raise ProtocolError("unknown_type", f"unknown message type {str(kind)[:40]!r}")
    try:
        return adapter.validate_python(raw)
    except ValidationError as exc:
        where = _null_number(exc)
        if where is not None:  # JSON.stringify(NaN) is null: tell the sender what happened
            raise ProtocolError(
                "non_finite",
                f"invalid {kind}: {where} is null; JSON has no NaN or Infinity (a NaN becomes "
                "null), send a finite number",
            ) from None
        raise ProtocolError("invalid_message", f"invalid {kind}: {_first_error(exc)}") from None


def _reject_constant(name: str) -> float:
    raise ProtocolError("non_finite", f"non-finite number {name} is not allowed")


def parse_client(text: str | bytes) -> Hello | State | Ping | Bye:
    """Parse and validate one client frame.

    Inbound fields are strict (no coercion of ``"1"``, ``true`` or ``"yes"``) and every number is
    bounded; ``null`` where a number belongs is reported as ``non_finite``.

    Raises
    ------
    ProtocolError
        ``malformed_json``, ``non_finite``, ``malformed_message``, ``unknown_type``,
        ``invalid_message``, ``too_complex`` or ``binary_not_expected``, with a message fit to
        send back.
    """
    if isinstance(text, str):
        check_complexity(text)
    return _parse(CLIENT_ADAPTER, text, ("hello", "state", "ping", "bye"))  # type: ignore[no-any-return]


def parse_server(text: str | bytes) -> Welcome | Patch | Pong | ErrorMsg | RoomState:
    """Parse and validate one server text frame (client side). Raises :class:`ProtocolError`."""
    return _parse(SERVER_ADAPTER, text, ("welcome", "patch", "pong", "error", "room"))  # type: ignore[no-any-return]


def encode(msg: BaseModel) -> str:
    """One message as a JSON text frame."""
    return msg.model_dump_json()


# ----------------------------------------------------------------------------- binary frames
#: Binary frame header: 4-byte magic, uint32 tick, uint32 count (little-endian).
BINARY_HEADER = struct.Struct("<4sII")
VERTICES_MAGIC = b"VTX1"  # count vertices follow as float32 x, y, z [m]
FACES_MAGIC = b"FAC1"  # count faces follow as uint32 i, j, k (counter-clockwise seen from outside)


def encode_vertices(tick: int, vertices: NDArray[np.floating[Any]]) -> bytes:
    """Binary frame of the current surface: header + (n, 3) float32 little-endian [m]."""
    v = np.ascontiguousarray(vertices, dtype="<f4")
    return BINARY_HEADER.pack(VERTICES_MAGIC, tick & 0xFFFFFFFF, v.shape[0]) + v.tobytes()


def encode_faces(faces: NDArray[np.integer[Any]]) -> bytes:
    """Binary frame of the triangle list: header (tick 0) + (m, 3) uint32 little-endian."""
    f = np.ascontiguousarray(faces, dtype="<u4")
    return BINARY_HEADER.pack(FACES_MAGIC, 0, f.shape[0]) + f.tobytes()


def decode_binary(frame: bytes) -> tuple[bytes, int, NDArray[Any]]:
    """Decode a binary frame into ``(magic, tick, (count, 3) array)``.

    Raises
    ------
    ProtocolError
        Unknown magic or a length that does not match the header.
    """
    if len(frame) < BINARY_HEADER.size:
        raise ProtocolError("malformed_binary", "binary frame shorter than its header")
    magic, tick, count = BINARY_HEADER.unpack_from(frame)
    dtype = {VERTICES_MAGIC: "<f4", FACES_MAGIC: "<u4"}.get(magic)
    if dtype is None:
        raise ProtocolError("malformed_binary", f"unknown binary frame {magic!r}")
    body = frame[BINARY_HEADER.size :]
    if len(body) != count * 12:
        raise ProtocolError("malformed_binary", "binary frame length does not match its count")
    return magic, tick, np.frombuffer(body, dtype=dtype).reshape(count, 3)


#: The JSON Schema dialect :func:`json_schema` writes.
JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

#: ``direction`` values of :func:`json_schema`: which messages the top-level ``oneOf`` admits.
SCHEMA_DIRECTIONS = ("both", "client", "server")


def _merge_defs(into: dict[str, Any], defs: dict[str, Any]) -> None:
    """Add ``defs`` to ``into``; a name already there must hold the same schema."""
    for name, sub in defs.items():
        if name in into and into[name] != sub:
            raise RuntimeError(f"two different JSON Schemas named {name!r}")  # pragma: no cover
        into[name] = sub


def _direction_schema(adapter: TypeAdapter[Any], defs: dict[str, Any]) -> dict[str, Any]:
    """One direction's discriminated union (``oneOf`` + ``discriminator``); its defs go to ``defs``."""
    schema = adapter.json_schema(mode="validation")
    _merge_defs(defs, schema.pop("$defs", {}))
    return schema


def json_schema(direction: str = "both") -> dict[str, Any]:
    """One JSON Schema (draft 2020-12) of the JSON text frames (``haptic protocol --schema``).

    Every message and nested model is a ``$defs`` entry named after its class (``Hello``,
    ``State``, ``Welcome``, ``RoomState``...). ``$defs/ClientMessage`` and ``$defs/ServerMessage``
    are the ``oneOf`` of the messages each direction sends. The top level is a ``oneOf`` of the
    messages ``direction`` selects (``"both"``: all nine, ``"client"``: client -> server,
    ``"server"``: server -> client), each with a required ``type`` constant, so exactly one branch
    matches a valid frame; ``discriminator`` (the OpenAPI keyword, an annotation to a JSON Schema
    validator) maps each ``type`` to its definition. ``protocol`` in ``hello`` and ``welcome`` is
    the constant :data:`PROTOCOL_VERSION`. Objects admit unknown fields (the server ignores them).
    The binary viewer frames are not JSON: docs/protocol.md, "Viewer stream", describes them.

    Parameters
    ----------
    direction
        ``"both"``, ``"client"`` or ``"server"`` (:data:`SCHEMA_DIRECTIONS`).

    Raises
    ------
    ValueError
        An unknown ``direction``.
    """
    if direction not in SCHEMA_DIRECTIONS:
        raise ValueError(
            f"direction must be one of {', '.join(SCHEMA_DIRECTIONS)}, not {direction!r}"
        )
    defs: dict[str, Any] = {}
    client = _direction_schema(CLIENT_ADAPTER, defs)
    server = _direction_schema(SERVER_ADAPTER, defs)
    client["description"] = "A message a client (user or viewer) sends to the server."
    server["description"] = "A JSON message the server sends to a client."
    for union in (client, server):
        for ref in union["discriminator"]["mapping"].values():
            message = defs[ref.rsplit("/", 1)[-1]]
            message["required"] = ["type", *(r for r in message.get("required", []) if r != "type")]
            if "protocol" in message["properties"]:
                message["properties"]["protocol"] = {
                    "const": PROTOCOL_VERSION,
                    "title": "Protocol",
                    "description": "The wire protocol version; the server refuses any other.",
                }
    defs["ClientMessage"] = client
    defs["ServerMessage"] = server
    chosen = {"both": (client, server), "client": (client,), "server": (server,)}[direction]
    mapping = {t: ref for union in chosen for t, ref in union["discriminator"]["mapping"].items()}
    which = {"both": "", "client": " (client -> server)", "server": " (server -> client)"}
    return {
        "$schema": JSON_SCHEMA_DIALECT,
        "title": f"haptic-collab wire protocol, version {PROTOCOL_VERSION}{which[direction]}",
        "description": "One JSON text frame: a message discriminated by its `type` (client -> "
        "server: hello, state, ping, bye; server -> client: welcome, patch, pong, error, room). "
        "Units are SI (m, N, N/m, Hz, s) unless a field name ends in _ms or _us. Binary frames "
        f"({FACES_MAGIC.decode()}, {VERTICES_MAGIC.decode()} and the viewer stream) are not "
        "JSON; docs/protocol.md describes them.",
        "oneOf": [{"$ref": ref} for union in chosen for ref in (r["$ref"] for r in union["oneOf"])],
        "discriminator": {"propertyName": "type", "mapping": mapping},
        "$defs": dict(sorted(defs.items())),
    }
