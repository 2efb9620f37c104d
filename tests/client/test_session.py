"""The client's protocol session: gains from patches, delay from round trips, stale patches."""

from __future__ import annotations

import pytest

from client.session import ClientSession
from shared.protocol import (
    DeviceInfo,
    ObjectInfo,
    Patch,
    PlaneModel,
    Pong,
    Welcome,
    encode,
)
from shared.stability import analyze

OBJ = ObjectInfo(
    n_vertices=6, n_faces=8, center_m=(0, 0, 0), radius_m=0.1, bounds_min_m=(-0.1, -0.1, -0.1),
    bounds_max_m=(0.1, 0.1, 0.1), top_m=(0, 0, 0.1), top_normal=(0, 0, 1), side_m=(0.1, 0, 0),
    side_normal=(1, 0, 0),
)  # fmt: skip


def patch(tick: int, k_o_eff: float = 300.0) -> str:
    return encode(
        Patch(
            tick=tick,
            primitive=PlaneModel(point=(0, 0, 0.1), normal=(0, 0, 1)),
            proxy_m=(0, 0, 0.1),
            normal=(0, 0, 1),
            penetration_m=0.002,
            in_contact=True,
            k_o=320.0,
            k_o_eff=k_o_eff,
            b_o=0.0,
        )  # fmt: skip
    )


def session(max_stiffness: float = 1000.0) -> ClientSession:
    s = ClientSession("A", device=DeviceInfo(max_stiffness_n_per_m=max_stiffness))
    s.receive(
        encode(Welcome(user_id="u1", name="A", role="user", sim_rate_hz=20.0, object=OBJ)), 0.0
    )
    return s


def pong(s: ClientSession, rtt_s: float, now: float) -> None:
    s.receive(encode(Pong(id=1, t_client_s=now - rtt_s, tick=0)), now)


def test_gains_are_stable_for_k_o_eff_and_below_the_device_limit():
    s = session(max_stiffness=150.0)
    up = s.receive(patch(1, k_o_eff=400.0), 0.1)
    assert up is not None and up.k_h <= 150.0 and up.i_gain > 0.0
    assert analyze(400.0, up.k_h, i_gain=up.i_gain).stable
    # designed with the margin: still stable if K_o_eff was overestimated by 30 %
    assert analyze(0.7 * 400.0 * 1.001, up.k_h, i_gain=up.i_gain).spectral_radius <= 1.0 + 1e-6


def test_measured_delay_is_counted_in_whole_ticks_and_makes_gains_safe():
    s = session()
    for i in range(20):
        pong(s, 0.22, 1.0 + 0.5 * i)  # 220 ms round trip at 20 Hz
    assert s.delay_ticks() == 4  # ceil((0.22 + 0.025) * 20) - 1
    up = s.receive(patch(2), 20.0)
    assert up is not None and up.delay_ticks == 4
    assert analyze(300.0, up.k_h, i_gain=up.i_gain, delay_ticks=4).stable


def test_one_stall_does_not_make_the_local_model_soft_for_long():
    s = session()
    for i in range(19):
        pong(s, 0.001, 1.0 + 0.5 * i)
    pong(s, 0.4, 11.0)  # one 400 ms stall among 1 ms round trips
    assert s.delay_ticks() == 0
    for i in range(5):
        pong(s, 0.4, 12.0 + 0.5 * i)  # a lasting change is taken into account
    assert s.delay_ticks() >= 7


def test_stale_patches_are_ignored_and_a_new_session_starts_afresh():
    s = session()
    assert s.receive(patch(10), 0.1) is not None
    assert s.receive(patch(9), 0.2) is None
    s.receive(
        encode(Welcome(user_id="u2", name="A", role="user", sim_rate_hz=20.0, object=OBJ)), 1.0
    )
    assert s.receive(patch(1), 1.1) is not None  # the restarted server counts from 1 again


@pytest.mark.parametrize("bad", ['{"type":"patch"}', "nope", '{"type":"room"}'])
def test_bad_server_frames_raise_protocol_errors(bad):
    from shared.protocol import ProtocolError

    with pytest.raises(ProtocolError):
        session().receive(bad, 0.0)
