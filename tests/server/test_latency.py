"""Latency injection: delay, jitter bounds, order, loss only on state streams, reproducible."""

from __future__ import annotations

import pytest

from haptic_collab.server.latency import LinkShaper
from haptic_collab.server.main import ServerOptions, build_link
from haptic_collab.server.room import Room
from haptic_collab.shared.protocol import LinkConditions


def test_constant_latency_delays_every_frame():
    sh = LinkShaper(LinkConditions(latency_ms=100.0), seed=1)
    assert sh.schedule(1.0, droppable=True) == pytest.approx(1.1)
    assert sh.schedule(2.0, droppable=False) == pytest.approx(2.1)


def test_jitter_stays_in_bounds_and_keeps_order():
    sh = LinkShaper(LinkConditions(latency_ms=100.0, jitter_ms=20.0), seed=2)
    last = 0.0
    for i in range(2000):
        now = i * 0.005
        at = sh.schedule(now, droppable=False)
        assert at is not None and at >= last
        assert 0.080 - 1e-9 <= at - now <= 0.120 + 0.02  # order may add up to one jitter span
        last = at


def test_loss_drops_only_droppable_frames_at_the_set_rate():
    sh = LinkShaper(LinkConditions(loss=0.1), seed=3)
    dropped = sum(sh.schedule(0.0, droppable=True) is None for _ in range(20000))
    assert 0.09 < dropped / 20000 < 0.11
    assert all(sh.schedule(0.0, droppable=False) is not None for _ in range(1000))


def test_same_seed_same_run():
    a = LinkShaper(LinkConditions(latency_ms=50, jitter_ms=10, loss=0.05), seed=9)
    b = LinkShaper(LinkConditions(latency_ms=50, jitter_ms=10, loss=0.05), seed=9)
    assert [a.schedule(i * 0.01, True) for i in range(500)] == [
        b.schedule(i * 0.01, True) for i in range(500)
    ]


@pytest.mark.parametrize(
    "kwargs",
    [
        {"latency_ms": -1},
        {"latency_ms": 60_000.001},
        {"jitter_ms": float("nan")},
        {"jitter_ms": float("inf")},
        {"loss": 1.0},
        {"loss": -0.1},
    ],
)
def test_absurd_link_settings_are_refused(kwargs):
    with pytest.raises(ValueError):
        LinkConditions(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"latency_ms": 70_000.0}, "latency_ms must be in [0, 60000] ms, got 70000.0"),
        ({"jitter_ms": -5.0}, "jitter_ms must be in [0, 60000] ms, got -5.0"),
        ({"latency_ms": float("nan")}, "latency_ms must be in [0, 60000] ms, got nan"),
        ({"loss": 1.0}, "loss must be in [0, 1), got 1.0"),
        ({"latency_ms": -1.0, "loss": 2.0}, "latency_ms must be in [0, 60000] ms, got -1.0"),
    ],
)
def test_haptic_server_names_the_bad_link_setting_in_one_line(kwargs, message):
    """``haptic server`` reports this message as ``haptic server: error: ...``."""
    with pytest.raises(ValueError) as info:
        build_link(ServerOptions(**kwargs))
    assert str(info.value) == message


def test_the_server_builds_the_conditions_it_shapes_and_announces_from_its_options():
    link = build_link(ServerOptions(latency_ms=100.0, jitter_ms=20.0, loss=0.02))
    assert link == LinkConditions(latency_ms=100.0, jitter_ms=20.0, loss=0.02) and link.active
    assert build_link(ServerOptions(latency_ms=60_000.0, loss=0.999)).active  # the bounds pass
    assert not build_link(ServerOptions()).active
    assert not LinkConditions().active
    assert LinkConditions(loss=0.01).active and LinkConditions(jitter_ms=1.0).active


@pytest.mark.parametrize(
    ("frame", "droppable"),
    [
        ('{"type":"state","seq":1,"probe_m":[0,0,0],"force_n":[0,0,0]}', True),
        ('{ "seq": 1, "type" : "state", "probe_m": [0, 0, 0]}', True),  # any key order, spacing
        ('{"type":"ping","id":1,"t_client_s":0.5}', True),
        ('{"type":"hello","protocol":1,"role":"user","name":"x"}', False),  # events: never lost
        ('{"type":"bye"}', False),
        ('{"name":"\\"type\\":\\"state\\"","type":"hello"}', False),  # no sniffing of the text
        ('{"type":["state"]}', False),  # hostile: refused by the room, never dropped silently
        ("[1, 2, 3]", False),
        ("not json", False),
        (b"\x00\x01binary", False),
        ("[" * 10000 + "]" * 10000, False),
    ],
)
def test_only_stream_frames_may_be_lost(frame, droppable):
    """The room decides which incoming frames loss injection may drop, from the message type."""
    assert Room.droppable(frame) is droppable
