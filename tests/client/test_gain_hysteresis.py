"""A contact whose K_o wanders across a gain-table cell boundary keeps the gains it renders while
the K_o stays where their design was checked (:meth:`shared.gain_table.GainTable.lookup`'s
``held``), in the client's own gains and in the server's recommendations."""

from __future__ import annotations

import pytest

from haptic_collab.server.gains import GainAdvisor
from haptic_collab.shared.protocol import DeviceInfo, Hello
from tests.support.sessions import plane_patch, welcomed_session


def test_a_k_o_wandering_over_a_cell_boundary_keeps_the_clients_gains() -> None:
    s = welcomed_session("A", "u1", b_h_max=10.0, gains="local")
    table = s.gain_table
    k0 = 300.0
    assert s.receive(plane_patch(1, k0), 0.05) is None  # waits for gains (the first contact)
    assert s.design_wanted is not None
    key, _ = s.design_wanted
    i = table.cell(k0)
    g1 = table.grid_point(i + 1)
    table.design(key, k0)
    table.design(key, 1.05 * g1)
    first = s.retry_waiting(0.06)
    assert first is not None and first.k_h == pytest.approx(table.lookup(key, k0).k_h)
    # the press stiffens the contact into the next cell: the gains in use stay (scaled as far as
    # their design was checked), where a fresh lookup would switch to the next cell's design
    s.receive(plane_patch(2, 1.05 * g1), 0.10)
    up = s.last_update
    kept = table.lookup(key, 1.05 * g1, held=i)
    fresh = table.lookup(key, 1.05 * g1)
    assert up is not None and kept is not None and fresh is not None
    assert up.k_h == pytest.approx(kept.k_h) and up.own_gain == pytest.approx(kept.own_gain)
    assert (fresh.k_h, fresh.own_gain) != pytest.approx((kept.k_h, kept.own_gain))
    # past the range that design was checked over, the K_o's own cell renders
    hi = table.lookup(key, table.grid_point(i)).k_o_range[1]
    s.receive(plane_patch(3, 1.01 * hi), 0.15)
    assert s.design_wanted is not None and table.cell(s.design_wanted[1]) == table.cell(1.01 * hi)


def test_the_servers_recommendation_keeps_the_cell_in_use_too() -> None:
    adv = GainAdvisor(sim_rate_hz=20.0)
    hello = Hello(
        protocol=1, role="user", name="A", local_model="p",
        device=DeviceInfo(max_stiffness_n_per_m=1000.0, max_damping_n_s_per_m=10.0),
    )  # fmt: skip
    k0 = 300.0
    key = adv.key("A", hello, 0.0, k0, k0)
    table = adv.table
    i = table.cell(k0)
    g1 = table.grid_point(i + 1)
    table.design(key, k0)
    table.design(key, 1.05 * g1)
    assert adv.recommend("A", hello, k_o_eff=k0, k_o_stiff=k0, b_o=0.0) is not None
    rec = adv.recommend("A", hello, k_o_eff=1.05 * g1, k_o_stiff=1.05 * g1, b_o=0.0)
    kept = table.lookup(key, 1.05 * g1, held=i)
    assert rec is not None and kept is not None
    assert rec.k_h == pytest.approx(kept.k_h) and rec.own_gain == pytest.approx(kept.own_gain)
    # another user at that K_o, with no cell in use, gets the next cell's design
    adv.key("B", hello, 0.0, k0, k0)
    other = adv.recommend("B", hello, k_o_eff=1.05 * g1, k_o_stiff=1.05 * g1, b_o=0.0)
    assert other is not None and other.k_h == pytest.approx(table.lookup(key, 1.05 * g1).k_h)
