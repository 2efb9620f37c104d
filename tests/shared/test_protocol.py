"""Wire protocol: valid messages round-trip, hostile frames get named errors, binary frames."""

from __future__ import annotations

import numpy as np
import pytest

from haptic_collab.shared.protocol import (
    PROTOCOL_VERSION,
    Hello,
    LinkConditions,
    Patch,
    PlaneModel,
    ProtocolError,
    State,
    Welcome,
    decode_binary,
    encode,
    encode_faces,
    encode_vertices,
    frame_size_bytes,
    json_schema,
    parse_client,
    parse_server,
)


def test_hello_and_state_round_trip():
    hello = Hello(protocol=PROTOCOL_VERSION, role="user", name="A")
    assert parse_client(encode(hello)) == hello
    state = State(
        seq=3, probe_m=(0.0, 0.0, 0.095), force_n=(0.0, 0.0, 1.2), in_contact=True, k_h=200.0
    )
    assert parse_client(encode(state)) == state
    # the type comes first so the server can classify a frame cheaply (latency injection)
    assert encode(state).startswith('{"type":"state"')


def test_patch_round_trip_on_the_client_side():
    patch = Patch(
        tick=7,
        primitive=PlaneModel(point=(0, 0, 0.1), normal=(0, 0, 1)),
        proxy_m=(0, 0, 0.1),
        normal=(0, 0, 1),
        penetration_m=0.002,
        in_contact=True,
        k_o=400.0,
        k_o_eff=350.0,
        b_o=0.0,
    )
    assert parse_server(encode(patch)) == patch


@pytest.mark.parametrize(
    "frame,code",
    [
        ("not json", "malformed_json"),
        ("[1, 2]", "malformed_message"),
        ('{"type": "launch_missiles"}', "unknown_type"),
        ('{"no_type": 1}', "unknown_type"),
        ('{"type":"state","seq":1,"probe_m":[0,0,NaN],"force_n":[0,0,0]}', "non_finite"),
        ('{"type":"state","seq":1,"probe_m":[0,0,Infinity],"force_n":[0,0,0]}', "non_finite"),
        ('{"type":"state","seq":1,"probe_m":[0,0,1e999],"force_n":[0,0,0]}', "invalid_message"),
        ('{"type":"state","seq":1,"probe_m":[0,0],"force_n":[0,0,0]}', "invalid_message"),
        ('{"type":"state","seq":-4,"probe_m":[0,0,0],"force_n":[0,0,0]}', "invalid_message"),
        ('{"type":"hello","protocol":1,"role":"admin","name":"x"}', "invalid_message"),
        ('{"type":"hello","protocol":1,"role":"user","name":"<script>"}', "invalid_message"),
        (
            '{"type":"hello","protocol":1,"role":"user","name":"' + "x" * 200 + '"}',
            "invalid_message",
        ),
        (b"\x00\x01binary", "binary_not_expected"),
        # parse cost is bounded before parsing: nesting depth and array lengths
        ("[" * 100000 + "]" * 100000, "too_complex"),
        ('{"type":"ping","id":1,"t_client_s":0,"pad":' + "[" * 70 + "]" * 70 + "}", "too_complex"),
        ('{"type":"ping","id":1,"t_client_s":0,"pad":[' + "0," * 600 + "0]}", "too_complex"),
        # no coercion: a string, a boolean or a float for an integer, a string for a boolean
        ('{"type":"state","seq":"1","probe_m":[0,0,0],"force_n":[0,0,0]}', "invalid_message"),
        ('{"type":"state","seq":true,"probe_m":[0,0,0],"force_n":[0,0,0]}', "invalid_message"),
        ('{"type":"state","seq":1.0,"probe_m":[0,0,0],"force_n":[0,0,0]}', "invalid_message"),
        (
            '{"type":"state","seq":1,"probe_m":[0,0,0],"force_n":[0,0,0],"in_contact":"yes"}',
            "invalid_message",
        ),
        ('{"type":"state","seq":1,"probe_m":["0",0,0],"force_n":[0,0,0]}', "invalid_message"),
        ('{"type":"hello","protocol":"1","role":"user","name":"x"}', "invalid_message"),
        ('{"type":"ping","id":1,"t_client_s":"0"}', "invalid_message"),
        # bounded: seq below 2**53, every number in a physical range
        (
            '{"type":"state","seq":' + "1" + "0" * 4000 + ',"probe_m":[0,0,0],"force_n":[0,0,0]}',
            "invalid_message",
        ),  # fmt: skip
        (
            '{"type":"state","seq":9007199254740992,"probe_m":[0,0,0],"force_n":[0,0,0]}',
            "invalid_message",
        ),  # fmt: skip
        (
            '{"type":"state","seq":1,"probe_m":[0,0,0],"force_n":[0,0,0],"penetration_m":1e308}',
            "invalid_message",
        ),
        (
            '{"type":"state","seq":1,"probe_m":[0,0,0],"force_n":[0,0,0],"k_h":-1}',
            "invalid_message",
        ),
        ('{"type":"state","seq":1,"probe_m":[1e9,0,0],"force_n":[0,0,0]}', "invalid_message"),
        ('{"type":"ping","id":1,"t_client_s":1e300}', "invalid_message"),
        ('{"type":"hello","protocol":1,"role":"user","name":"x","token":""}', "invalid_message"),
        # JSON has no NaN: JSON.stringify(NaN) gives null, reported as such
        ('{"type":"state","seq":1,"probe_m":[0,0,null],"force_n":[0,0,0]}', "non_finite"),
        ('{"type":"state","seq":1,"probe_m":[0,0,0],"force_n":[0,0,0],"k_h":null}', "non_finite"),
    ],
)
def test_hostile_frames_get_named_errors(frame, code):
    with pytest.raises(ProtocolError) as info:
        parse_client(frame)
    assert info.value.code == code
    assert len(str(info.value)) < 300  # fit to send back


def test_null_for_a_number_says_json_has_no_nan():
    with pytest.raises(ProtocolError) as info:
        parse_client('{"type":"state","seq":1,"probe_m":[0,0,null],"force_n":[0,0,0]}')
    assert info.value.code == "non_finite" and "NaN" in str(info.value)
    assert "probe_m.2" in str(info.value)


def test_valid_values_still_pass_and_optional_nulls_stay_allowed():
    # integers where floats are expected are not a coercion; rtt_ms may be null (unknown yet)
    s = parse_client(
        '{"type":"state","seq":9007199254740991,"probe_m":[0,0,1],"force_n":[0,0,2],'
        '"in_contact":true,"k_h":300,"rtt_ms":null,"penetration_m":-0.5}'
    )
    assert isinstance(s, State) and s.seq == 2**53 - 1 and s.rtt_ms is None and s.k_h == 300.0


def test_hello_token_is_carried_but_never_shown():
    h = parse_client(
        '{"type":"hello","protocol":1,"role":"viewer","name":"v","token":"s3cret-token-value"}'
    )
    assert isinstance(h, Hello) and h.token == "s3cret-token-value"
    assert "s3cret" not in repr(h) and "s3cret" not in str(h)


def test_frame_size_counts_bytes_not_characters():
    assert frame_size_bytes("abc") == 3
    assert frame_size_bytes("\u00e9" * 10) == 20  # two bytes each in UTF-8
    assert frame_size_bytes("\U0001f600") == 4
    assert frame_size_bytes(b"\x00" * 7) == 7


def test_binary_vertex_and_face_frames():
    v = np.random.default_rng(0).normal(size=(100, 3))
    magic, tick, arr = decode_binary(encode_vertices(42, v))
    assert magic == b"VTX1" and tick == 42 and np.allclose(arr, v, atol=1e-6)
    f = np.arange(30).reshape(10, 3)
    magic, tick, arr = decode_binary(encode_faces(f))
    assert magic == b"FAC1" and (arr == f).all()
    with pytest.raises(ProtocolError):
        decode_binary(b"VTX1" + b"\x00" * 4 + b"\x05\x00\x00\x00" + b"\x00" * 12)
    with pytest.raises(ProtocolError):
        decode_binary(b"XXXX" + b"\x00" * 8)


CLIENT_TYPES = ("hello", "state", "ping", "bye")
SERVER_TYPES = ("welcome", "patch", "pong", "error", "room")


def test_schema_lists_every_message():
    schema = json_schema()
    defs = schema["$defs"]
    tags = {}
    for ref in schema["oneOf"]:
        message = defs[ref["$ref"].removeprefix("#/$defs/")]
        assert "type" in message["required"]
        tags[message["properties"]["type"]["const"]] = ref["$ref"]
    assert tags == schema["discriminator"]["mapping"]
    assert set(tags) == set(CLIENT_TYPES + SERVER_TYPES)
    assert [r["$ref"] for r in defs["ClientMessage"]["oneOf"]] == [
        "#/$defs/Hello", "#/$defs/State", "#/$defs/Ping", "#/$defs/Bye"
    ]  # fmt: skip
    assert json_schema("server")["oneOf"] == defs["ServerMessage"]["oneOf"]
    with pytest.raises(ValueError, match="direction"):
        json_schema("sideways")


def _welcome_frame(link: str) -> str:
    obj = (
        '{"n_vertices":4,"n_faces":4,"center_m":[0,0,0],"radius_m":0.1,"bounds_min_m":[0,0,0],'
        '"bounds_max_m":[0,0,0],"top_m":[0,0,0.1],"top_normal":[0,0,1],"side_m":[0.1,0,0],'
        '"side_normal":[1,0,0]}'
    )
    return (
        '{"type":"welcome","user_id":"u1","name":"A","role":"user","sim_rate_hz":20.0,'
        f'"object":{obj},"link":{link}}}'
    )


def test_announced_link_conditions_round_trip_within_their_bounds():
    link = LinkConditions(latency_ms=60_000.0, jitter_ms=20.0, loss=0.999)
    welcome = parse_server(_welcome_frame(encode(link)))
    assert isinstance(welcome, Welcome) and welcome.link == link and welcome.link.active


@pytest.mark.parametrize(
    "link",
    [
        '{"latency_ms":-1}',
        '{"latency_ms":60001}',
        '{"jitter_ms":1e9}',
        '{"loss":1.0}',
        '{"loss":-0.01}',
    ],
)
def test_link_conditions_out_of_range_are_refused_on_the_wire(link):
    with pytest.raises(ProtocolError) as info:
        parse_server(_welcome_frame(link))
    assert info.value.code == "invalid_message" and "link" in str(info.value)


def test_the_schema_states_the_link_bounds():
    props = json_schema()["$defs"]["LinkConditions"]["properties"]
    for name in ("latency_ms", "jitter_ms"):
        assert (props[name]["minimum"], props[name]["maximum"]) == (0, 60_000)
    assert (props["loss"]["minimum"], props["loss"]["exclusiveMaximum"]) == (0, 1)
