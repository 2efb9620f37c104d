"""The table of gain designs (shared.gains.table), its designs re-checked on a finer lattice of hands
than the design's own (:mod:`tests.support.hand_lattice`): lookups, scaling across a cell,
fallbacks while a cell is designed, and refused input."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from haptic_collab.shared.felt_stiffness import felt_responses
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
from haptic_collab.shared.gains.design import GainDesign, design_gains, design_gains_modes
from haptic_collab.shared.gains.interim import verify_gains
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.table import (
    GainTable,
    cell_k_o_range,
    design_cell,
    design_cell_modes,
)
from tests.support.hand_lattice import SERVO_HZ, T, worst_on_lattice

MARGIN = 0.15  # design_gains' default
K_H_MAX = 1000.0  # Phantom Desktop limits (client.devices.profiles)
B_H_MAX = 10.0


# ----------------------------------------------------------------------------------- GainTable
def _key(mode: str = "p") -> GainKey:
    return GainKey(
        servo_rate_hz=SERVO_HZ,
        sim_rate_hz=20.0,
        delay_ticks=0,
        mode=mode,
        margin=MARGIN,
        k_h_max=K_H_MAX,
        b_h_max=B_H_MAX,
    )


def test_table_lookup_is_none_until_the_cell_is_designed() -> None:
    table = GainTable()
    key = _key()
    assert table.lookup(key, 1000.0) is None
    assert table.fallback(key, 1000.0) is None
    assert len(table) == 0
    d = table.design(key, 1000.0)
    i = table.cell(1000.0)
    g0, g1 = table.grid_point(i), table.grid_point(i + 1)
    assert g0 <= 1000.0 < g1
    assert table.lookup(key, 1000.0) == d
    base = table.lookup(key, g0)
    assert base is not None and base.scale_max > 1.0
    for k_o in (g0, 1000.0, 0.5 * (g0 + g1), g1 * (1.0 - 1e-9)):
        # anywhere in the cell: the cell's design scaled to the reported K_o, K_h within the
        # device's stiffness
        got = table.lookup(key, k_o)
        assert got is not None and got == got.at(k_o)
        s = min(k_o / g0, base.scale_max)
        assert got.k_h == pytest.approx(base.k_h * s) and got.k_h <= K_H_MAX
        assert got.own_gain * got.k_h == pytest.approx(base.own_gain * base.k_h)
        assert (got.b_h, got.proxy_hold) == (base.b_h, base.proxy_hold)
        assert got.k_o_range == pytest.approx((base.k_o_range[0] * s, base.k_o_range[1]))
    assert table.lookup(key, g1 * 1.0001) is None  # the next cell is not designed
    assert table.lookup(_key("pi"), 1000.0) is None  # nor another key's
    assert len(table) == 1


@pytest.mark.parametrize("mode", ["p", "pi"])
def test_table_design_covers_its_whole_cell(mode: str) -> None:
    table = GainTable()
    key = _key(mode)
    table.design(key, 1000.0)
    i = table.cell(1000.0)
    g0, g1 = table.grid_point(i), table.grid_point(i + 1)
    for k_o in (g0, 1000.0, g1 * (1.0 - 1e-9)):  # the gains served for it, on a finer lattice
        d = table.lookup(key, k_o)
        assert d is not None and d.k_h <= K_H_MAX and d.b_h <= B_H_MAX
        rho, where = worst_on_lattice(
            d, [(1.0 - MARGIN) * k_o, k_o, g1], sim_rate_hz=20.0, delay_ticks=0
        )
        assert rho < 1.0, where


def _felt_spread_over_cell(d: GainDesign | GainTable, g0: float, g1: float, key: GainKey) -> float:
    """How much the felt stiffness |dF/dx| / K_o at 0.5, 1 and 2 Hz (below where a damper is felt)
    changes over K_o = g0, sqrt(g0 g1) and the top of the cell, the largest over the three
    frequencies: fixed gains ``d``, or the gains a table ``d`` serves for each K_o."""
    q = []
    for k_o in (g0, math.sqrt(g0 * g1), g1 * (1.0 - 1e-9)):
        served = d.lookup(key, k_o) if isinstance(d, GainTable) else d
        assert served is not None
        r = felt_responses(
            (0.5, 1.0, 2.0),
            k_o=k_o,
            k_h=served.k_h,
            i_gain=served.i_gain,
            b_h=served.b_h,
            own_gain=served.own_gain,
            servo_period_s=T,
            rate_ratio=key.rates.ratio,
            delay_ticks=key.delay_ticks,
            proxy_hold=served.proxy_hold,
        )[:, 0]
        q.append(np.abs(r) / k_o)
    qs = np.array(q)
    return float(np.max(qs.max(axis=0) - qs.min(axis=0)))


@pytest.mark.slow
def test_table_design_feels_like_the_object_across_its_whole_cell() -> None:
    # a table design serves every K_o reported in its cell, scaled to it; with 4 ticks of delay
    # the felt response depends on K_h / K_o: the same gains for the whole cell (judged across
    # it) feel 5-10 % softer at its top than at its lower end (300 N/m's cell at 20 Hz, 0.5-2
    # Hz), scaled ones the same within 0.5 %
    key = replace(_key("p"), delay_ticks=4)
    table = GainTable()
    i = table.cell(300.0)
    g0, g1 = table.grid_point(i), table.grid_point(i + 1)
    table.design(key, 300.0)
    fixed = design_gains(
        g0,
        sim_rate_hz=20.0,
        delay_ticks=4,
        mode="p",
        margin=MARGIN,
        k_o_hi=cell_k_o_range(key, i, table.grid_ratio)[1],
        k_h_max=K_H_MAX,
        b_h_max=B_H_MAX,
        own_force=True,
        felt_k_os=[g0, math.sqrt(g0 * g1), g1],
        stiffer_by=key.stiffer_by,
    )
    assert fixed.scale_max == 1.0
    assert _felt_spread_over_cell(table, g0, g1, key) < 0.005
    assert _felt_spread_over_cell(fixed, g0, g1, key) > 0.03
    for k_o in (g0, 300.0, g1 * (1.0 - 1e-9)):  # each stable on a finer hand lattice
        d = table.lookup(key, k_o)
        assert d is not None
        rho, where = worst_on_lattice(
            d, [(1.0 - MARGIN) * k_o, k_o, g1], sim_rate_hz=20.0, delay_ticks=4
        )
        assert rho < 1.0, where


def test_scaled_design_serves_the_gains_it_checked() -> None:
    # every scale a cell's design is served at passes the design's own acceptance test, and the
    # design's top scale keeps K_h within the device's stiffness
    key = _key("p")
    table = GainTable()
    for k_o in (100.0, 900.0):
        i = table.cell(k_o)
        g0, g1 = table.grid_point(i), table.grid_point(i + 1)
        table.design(key, k_o)
        for k in (g0, math.sqrt(g0 * g1), g1 * (1.0 - 1e-9)):
            d = table.lookup(key, k)
            assert d is not None and d.k_h <= K_H_MAX
            ok, rho = verify_gains(
                key,
                i,
                table.grid_ratio,
                table.hand_box,
                k_h=d.k_h,
                i_gain=d.i_gain,
                b_h=d.b_h,
                proxy_hold=d.proxy_hold,
                own_gain=d.own_gain,
                k_o_scale=min(k / g0, table.grid_ratio),
            )
            assert ok, (k_o, k, rho)


def _relative(d: GainDesign, k_o: float) -> tuple[float, float, float]:
    return d.k_h / k_o, d.i_gain / k_o, d.b_h / k_o


def test_table_fallback_is_never_stiffer_relative_to_k_o_than_a_designed_cell() -> None:
    table = GainTable()
    key = _key()
    for k in (300.0, 3000.0):
        table.design(key, k)
    # each designed cell's own gains, at its grid point
    designed = {k: table.lookup(key, table.grid_point(table.cell(k))) for k in (300.0, 3000.0)}
    for k_o in (120.0, 200.0, 299.0, 500.0, 1000.0, 2900.0, 5000.0, 20000.0):
        fb = table.fallback(key, k_o)
        assert fb is not None
        # the worst case over the requested cell: K_o at its lower grid point
        got = _relative(fb, table.grid_point(table.cell(k_o)))
        assert any(
            all(a <= b * (1.0 + 1e-12) for a, b in zip(got, _relative(d, d.k_o), strict=True))
            for d in designed.values()
            if d is not None
        ), (k_o, fb)
        assert fb.k_h <= K_H_MAX and fb.b_h <= B_H_MAX


def test_table_fallback_compensation_has_no_step_at_a_cell_boundary() -> None:
    # the cell below's C_h keeps its share of the K_o reported itself: a K_o crossing a cell
    # boundary (a press held into a stiffening object) sees the same C_h K_o on both sides
    table = GainTable()
    key = _key()
    table.design(key, 300.0)
    d = table.lookup(key, table.grid_point(table.cell(300.0)))
    assert d is not None and d.own_gain > 0.0
    share = d.own_gain * d.k_o
    for up in (2, 3, 5):
        edge = table.grid_point(table.cell(300.0) + up)
        for k in (edge * (1.0 - 1e-9), edge, edge * 1.05):
            fb = table.fallback(key, k)
            assert fb is not None and fb.own_gain * k == pytest.approx(share, rel=1e-9)


@pytest.mark.parametrize("mode", ["p", "pi"])
def test_table_fallback_gains_are_stable_for_the_box_at_the_stiffness_they_are_served_for(
    mode: str,
) -> None:
    """Only the 277 N/m cell is designed; the object stiffens to 539 N/m (six cells up) while that
    cell is being designed: the fallback renders the 277 N/m gains on a 539 N/m object."""
    table = GainTable()
    key = _key(mode)
    table.design(key, 300.0)
    k_o = table.grid_point(table.cell(300.0) + 6) * 1.0999
    fb = table.fallback(key, k_o)
    assert fb is not None
    rho, where = worst_on_lattice(
        fb, [k_o], sim_rate_hz=20.0, delay_ticks=0, hands=DEFAULT_HAND_BOX.hands()
    )
    assert rho < 1.0, f"fallback unstable (spectral radius {rho:.4f}) for {where}"


def test_a_cell_is_checked_up_to_the_one_tick_stiffness_of_a_massive_or_relaxing_object() -> None:
    # a spring's cell is checked up to 1.25 times its top; an object that reports B_o is as stiff
    # as K_o + B_o over a step push's first simulation period, and its cell is checked up to
    # that where it is higher (docs/gains.md)
    table = GainTable()
    i = table.cell(300.0)
    top = table.grid_point(i + 1)
    key = replace(_key(), stiffer_by=0.25)
    assert cell_k_o_range(key, i, table.grid_ratio)[1] == pytest.approx(1.25 * top)
    assert cell_k_o_range(replace(key, b_o=50.0), i, table.grid_ratio)[1] == pytest.approx(
        1.25 * top
    )
    lo, hi = cell_k_o_range(replace(key, b_o=472.0), i, table.grid_ratio)
    assert hi == pytest.approx(top + 472.0)
    assert lo == pytest.approx((1.0 - MARGIN) * table.grid_point(i))


def test_table_refuses_bad_grid_and_stiffness() -> None:
    with pytest.raises(ValueError):
        GainTable(grid_ratio=1.0)
    table = GainTable()
    for bad in (0.0, -5.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            table.cell(bad)
        with pytest.raises(ValueError):
            table.lookup(_key(), bad)


@pytest.mark.parametrize(
    ("k_o", "sim_rate_hz", "delay_ticks", "b_o"),
    [
        pytest.param(300.0, 100.0, 5, 0.0, marks=pytest.mark.slow),  # 5 ticks: a long design
        # each designs its cell twice afresh (half a minute on a fresh checkout): slow too
        pytest.param(3000.0, 10.0, 1, 0.0, marks=pytest.mark.slow),
        pytest.param(300.0, 100.0, 1, 391.0, marks=pytest.mark.slow),
    ],
)
def test_both_local_models_designed_at_once_are_each_the_design_made_alone(
    k_o: float, sim_rate_hz: float, delay_ticks: int, b_o: float
) -> None:
    # the fidelity benchmark designs P and PI together, searching their common (compensated)
    # candidates once: each must be exactly the design the client makes for its own key
    # (a cell below, above the device's stiffness with the plane's candidates, and with a B_o)
    key = replace(
        _key(), sim_rate_hz=sim_rate_hz, delay_ticks=delay_ticks, b_o=b_o, stiffer_by=0.25
    )
    table = GainTable()
    cell = table.cell(k_o)
    both = design_cell_modes(key, cell, table.grid_ratio, table.hand_box)
    for mode in ("p", "pi"):
        alone = design_cell(replace(key, mode=mode), cell, table.grid_ratio, table.hand_box)
        assert both[mode] == alone
    assert both["p"].mode == "p" and both["p"].i_gain == 0.0


def test_a_pi_design_with_no_stable_integral_is_the_p_design_when_both_are_made() -> None:
    # no damper and 4 ticks of delay: no integral holds the box, and PI renders the P design
    # (as design_gains does for PI alone)
    args = {"sim_rate_hz": 20.0, "delay_ticks": 4, "b_h_max": 0.0, "k_h_max": K_H_MAX}
    both = design_gains_modes(300.0, **args)
    assert both["pi"] == both["p"] == design_gains(300.0, mode="pi", **args)
    assert both["pi"].mode == "p"
    with pytest.raises(ValueError, match="mode"):
        design_gains_modes(300.0, modes=())
