"""`haptic protocol --schema` is one JSON Schema a validator can use on real frames.

The frames come from a real exchange: a :class:`client.session.ClientSession` user and a viewer
against an in-process server on loopback; the schema is what the command prints.
"""

from __future__ import annotations

import asyncio
import json
import time

import pytest
from websockets.asyncio.client import connect

from haptic_collab.cli import main
from haptic_collab.client.session import ClientSession, ServoSample
from haptic_collab.server.app import ServerApp
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import Room
from haptic_collab.shared.protocol import Bye, ProtocolError, encode, parse_client, parse_server

jsonschema = pytest.importorskip("jsonschema")

SIM_RATE = 20.0


def printed_schema(capsys: pytest.CaptureFixture[str], *args: str) -> dict:
    assert main(["protocol", "--schema", *args]) == 0
    return json.loads(capsys.readouterr().out)


def validator(schema: dict):
    cls = jsonschema.validators.validator_for(schema)
    assert cls is jsonschema.Draft202012Validator
    cls.check_schema(schema)  # a valid draft 2020-12 document
    return cls(schema)


async def real_frames() -> tuple[dict[str, str], dict[str, str]]:
    """One frame of each kind a client sends and the server sends, from a real exchange."""
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2))
    app = ServerApp(Room(world, SIM_RATE), "127.0.0.1", 0)
    await app.start()
    sent: dict[str, str] = {}
    got: dict[str, str] = {}
    try:
        url = f"ws://127.0.0.1:{app.port}/ws"
        user = ClientSession("A")
        async with connect(url) as ws, connect(url) as viewer_ws:
            sent["hello"] = user.hello(time.monotonic())
            await ws.send(sent["hello"])
            got["welcome"] = str(await asyncio.wait_for(ws.recv(), 10.0))
            user.receive(got["welcome"], time.monotonic())
            top = json.loads(got["welcome"])["object"]["top_m"]
            sample = ServoSample(
                probe_m=(top[0], top[1], top[2] - 0.002),
                force_n=(0.0, 0.0, 0.3),
                penetration_m=0.002,
                in_contact=True,
                k_h=150.0,
                i_gain=800.0,
                servo_rate_hz=1000.0,
                period_us_p99=1100.0,
            )
            sent["ping"] = user.ping(time.monotonic())
            await ws.send(sent["ping"])
            await ws.send(sent["hello"])  # a second hello: a (soft) error
            await viewer_ws.send(ClientSession("V", role="viewer").hello())
            deadline = time.monotonic() + 20.0
            while not {"patch", "pong", "error"} <= got.keys() and time.monotonic() < deadline:
                sent["state"] = user.state(sample)
                await ws.send(sent["state"])
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    got.setdefault(json.loads(frame)["type"], frame)
            while "room" not in got and time.monotonic() < deadline:
                frame = await asyncio.wait_for(viewer_ws.recv(), 10.0)
                if isinstance(frame, str) and json.loads(frame)["type"] == "room":
                    got["room"] = frame
            sent["bye"] = encode(Bye())
            await ws.send(sent["bye"])
    finally:
        await app.stop()
    return sent, got


async def test_real_frames_validate_against_the_printed_schema(capsys):
    schema = printed_schema(capsys)
    check = validator(schema)
    sent, got = await real_frames()
    assert sent.keys() >= {"hello", "state", "ping", "bye"}
    assert got.keys() >= {"welcome", "patch", "pong", "error", "room"}, got.keys()
    assert json.loads(got["error"])["code"] == "duplicate_hello"
    for kind, frame in [*sent.items(), *got.items()]:
        errors = [e.message for e in check.iter_errors(json.loads(frame))]
        assert errors == [], (kind, errors)
    # a validator can check one direction: what a client sends, or what the server sends
    client_only = validator(printed_schema(capsys, "--direction", "client"))
    server_only = validator(printed_schema(capsys, "--direction", "server"))
    for frame in sent.values():
        assert client_only.is_valid(json.loads(frame)) and not server_only.is_valid(
            json.loads(frame)
        )
    for frame in got.values():
        assert server_only.is_valid(json.loads(frame)) and not client_only.is_valid(
            json.loads(frame)
        )


HELLO = {"type": "hello", "protocol": 1, "role": "user", "name": "A"}
STATE = {"type": "state", "seq": 1, "probe_m": [0, 0, 0.05], "force_n": [0, 0, 0.3]}


@pytest.mark.parametrize(
    "bad",
    [
        {**HELLO, "name": "two words"},  # names are [A-Za-z0-9_.-]
        {**HELLO, "role": "admin"},
        {k: v for k, v in HELLO.items() if k != "name"},
        {k: v for k, v in STATE.items() if k != "type"},  # no type: not a message
        {**STATE, "type": "teleport"},
        {**STATE, "probe_m": [0, 0]},  # positions have three components
        {**STATE, "force_n": [0, 0, "0.3"]},
        {**STATE, "seq": -1},
    ],
)
def test_the_schema_refuses_what_the_server_refuses(capsys, bad):
    check = validator(printed_schema(capsys))
    assert not check.is_valid(bad)
    with pytest.raises(ProtocolError):
        parse_client(json.dumps(bad))


WELCOME = {
    "type": "welcome",
    "user_id": "u1",
    "name": "A",
    "role": "user",
    "sim_rate_hz": 20.0,
    "object": {
        "n_vertices": 4,
        "n_faces": 4,
        "center_m": [0, 0, 0],
        "radius_m": 0.1,
        "bounds_min_m": [-0.1, -0.1, -0.1],
        "bounds_max_m": [0.1, 0.1, 0.1],
        "top_m": [0, 0, 0.1],
        "top_normal": [0, 0, 1],
        "side_m": [0.1, 0, 0],
        "side_normal": [1, 0, 0],
    },
}


@pytest.mark.parametrize(
    ("link", "ok"),
    [
        ({"latency_ms": 100, "jitter_ms": 20, "loss": 0.02}, True),
        ({"latency_ms": 60000, "jitter_ms": 0, "loss": 0.999}, True),
        ({"latency_ms": -1}, False),
        ({"jitter_ms": 60001}, False),
        ({"loss": 1}, False),
    ],
)
def test_the_schema_bounds_the_announced_link_conditions_as_the_server_does(capsys, link, ok):
    check = validator(printed_schema(capsys, "--direction", "server"))
    frame = {**WELCOME, "link": link}
    assert check.is_valid(frame) is ok
    if ok:
        parse_server(json.dumps(frame))
    else:
        with pytest.raises(ProtocolError):
            parse_server(json.dumps(frame))


def test_minimal_hand_written_messages_pass_and_the_version_is_pinned(capsys):
    check = validator(printed_schema(capsys))
    assert not check.is_valid({**HELLO, "protocol": 2})  # the server answers protocol_version
    for good in (HELLO, STATE, {"type": "bye"}, {"type": "ping", "id": 1, "t_client_s": 0.5}):
        assert check.is_valid(good), good
        parse_client(json.dumps(good))  # and the server takes them
