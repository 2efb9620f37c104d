"""The honest fidelity benchmark's 1-D parts (docs/fidelity.md): objects the design did not see, peers
with the local model's information and their tunings, servo imperfections."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from haptic_collab.bench.fidelity import (
    _alone_plane_jobs,
    _checked_plane_cell,
    _design_cell,
    _gain_key,
    _identified_plane_jobs,
    _k_o_designed,
    _plane_cell,
    _planes,
    _table,
)
from haptic_collab.research.fidelity_1d import simulate
from haptic_collab.research.fidelity_cases import (
    IMPACT,
    OBJECTS,
    PRESS,
    SLS,
    SPRING,
    SPRING_SOFTER,
    SPRING_STIFFER,
    STIFFENING,
    TAP,
    Cell,
    ObjectModel,
    RunOptions,
    felt_depth_m,
    felt_trajectory,
    felt_window_s,
)
from haptic_collab.research.fidelity_metrics import cell_metrics, felt_response
from haptic_collab.research.fidelity_schemes import (
    PRODUCT_GAIN_TRANSFER_S,
    PRODUCT_PLANE_CHECK_S,
    SCHEMES,
    DeviceModel,
    Rendering,
    TableCell,
    TableGains,
    peer_renderings,
    rendering_for,
)
from haptic_collab.shared.full_loop import DEFAULT_HAND, DEFAULT_HAND_BOX, Hand, ProxyHold
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.table import GainTable

DIRECT = Rendering("direct", "direct")
FMAX = 7.9


def _felt(r: Rendering, obj: ObjectModel, k_o: float, rate: float, delay_ms: float, hz: float):
    cell = Cell(
        r, k_o, rate, delay_ms, None, felt_trajectory(hz, felt_depth_m(k_o, FMAX, obj)), obj
    )
    q = felt_response(simulate([cell]), [cell])[0]
    assert q is not None, (r.scheme, obj.name, hz)
    return q


@pytest.mark.parametrize("obj", [SPRING, SPRING_STIFFER, SLS, STIFFENING], ids=lambda o: o.name)
def test_direct_rendering_fast_and_undelayed_feels_each_object_as_itself(obj) -> None:
    # the reference of the felt response is the object's own impedance: a 1 kHz simulation of it
    # with no delay must read as 1 (within the 1-ms lag of one tick: phase < 0.02 rad at 1 Hz)
    q = _felt(DIRECT, obj, 300.0, 1000.0, 0.0, 1.0)
    assert abs(q) == pytest.approx(1.0, abs=0.02)
    assert abs(math.atan2(q.imag, q.real)) < 0.05


def test_the_objects_differ_from_the_design_model_as_stated() -> None:
    k = 300.0
    assert SPRING_STIFFER.impedance(k, 1.0, 0.0) == pytest.approx(1.2 * k)
    assert SPRING_SOFTER.impedance(k, 1.0, 0.0) == pytest.approx(0.8 * k)
    # the viscoelastic object: twice as stiff to a fast press as at rest, K_o when relaxed
    assert abs(SLS.impedance(k, 0.01, 0.0)) == pytest.approx(k, rel=0.01)
    assert SLS.peak_stiffness(k, 0.0) == pytest.approx(2.0 * k)
    # strain stiffening: e times stiffer 10 mm in; the static depth inverts the static force
    assert STIFFENING.impedance(k, 1.0, 10e-3).real == pytest.approx(math.e * k)
    f = STIFFENING.static_force_n(k, np.array([0.0, 2e-3, 8e-3]))
    assert STIFFENING.static_depth_m(k, f) == pytest.approx([0.0, 2e-3, 8e-3])
    # a press held long enough settles where the relaxed object holds the force
    r = Rendering("mmt", "mmt", k_h=1000.0, b_h=5.0)
    for obj in OBJECTS:
        cell = Cell(r, k, 20.0, 0.0, DEFAULT_HAND, PRESS, obj)
        m = cell_metrics(simulate([cell]), [cell])[0]
        assert m.stable, obj.name


def test_the_simulation_reports_b_o_as_the_worlds_objects_do() -> None:
    # B_o is the first tick's stiffness from rest less the static one (the FEM solid's and the
    # balloon's contact_damping). For the viscoelastic object with mass, one implicit-Euler tick
    # of a step push F from rest solves m x/h^2 + k_1 x + k_2 (x - q) = F, q = h/(tau+h) x
    k, rate, f = 300.0, 50.0, 1.0
    h, tau, m = 1.0 / rate, SLS.relax_time_s, SLS.mass_kg
    x1 = f / (m / h**2 + k + k * (1.0 - h / (tau + h)))
    assert SLS.one_tick_stiffness(k, rate) == pytest.approx(f / x1)
    assert SLS.reported_b_o(k, rate) == pytest.approx(f / x1 - k)
    # the surface mass dominates at a fast simulation: 200 N/m at 100 Hz, 2 N/m at 10 Hz
    assert SLS.reported_b_o(100.0, 100.0) - SLS.reported_b_o(100.0, 10.0) > 150.0
    # springs and the quasi-static stiffening object answer at once: no B_o, whatever their error
    for obj in (SPRING, SPRING_SOFTER, SPRING_STIFFER, STIFFENING):
        assert obj.reported_b_o(k, rate) == 0.0
    with pytest.raises(ValueError):
        SLS.one_tick_stiffness(k, 0.0)


def test_mmt_is_the_compensated_p_model_with_k_h_equal_to_k_o() -> None:
    # what a re-analysis of the benchmark measured: for K_o within the device's stiffness the product's design is a
    # plane at the rest surface with K_o, the same information MMT renders
    k = 300.0
    mmt = Rendering("mmt", "mmt", k_h=1000.0, b_h=2.5)
    lp = Rendering("local-p", "coupling", k_h=k, b_h=2.5, own_gain=1.0 / k)
    cells = [Cell(r, k, 20.0, 50.0, DEFAULT_HAND, TAP) for r in (mmt, lp)]
    run = simulate(cells)
    np.testing.assert_allclose(run.x[0], run.x[1], atol=1e-12)
    np.testing.assert_allclose(run.f[0], run.f[1], atol=1e-9)


def test_force_jacobian_renders_the_tangent_stiffness_that_mmt_caps() -> None:
    # 10 mm into the stiffening object (tangent 2.7 K_o): the jacobian's force follows the
    # simulation's own force at 1 Hz; MMT renders a plane capped at the device's stiffness
    k = 300.0
    jac = Rendering("force-jacobian", "jacobian", k_h=1000.0)
    q = _felt(jac, STIFFENING, k, 100.0, 0.0, 1.0)
    assert abs(q) == pytest.approx(1.0, abs=0.05)
    capped = Rendering("mmt", "mmt", k_h=k)  # a cap at the reported K_o
    q2 = _felt(capped, STIFFENING, k, 100.0, 0.0, 1.0)
    assert abs(q2) < 0.8


def test_the_virtual_coupling_tool_sits_where_coupling_and_object_balance() -> None:
    # a massless tool in equilibrium: the hand feels the coupling in series with the object
    kc, k = 1000.0, 1000.0
    vc = Rendering("virtual-coupling", "tool", k_h=kc)
    q = _felt(vc, SPRING, k, 100.0, 0.0, 0.5)
    assert abs(q) == pytest.approx(kc / (kc + k), rel=0.03)


def test_a_static_plane_renders_the_stiffness_reported_not_the_objects() -> None:
    wall = peer_renderings("static-local", k_o=300.0, sim_rate_hz=20.0)[1]
    assert wall.kind == "wall" and wall.k_h == 300.0
    q = _felt(wall, SPRING_SOFTER, 300.0, 20.0, 100.0, 1.0)
    assert abs(q) == pytest.approx(1.0 / 0.8, rel=0.05)  # 25 % too stiff, delay or not


def test_two_port_tdpa_gives_back_no_more_than_the_object_returned() -> None:
    hand = Hand(0.3, 5.0, 300.0)
    one, two = peer_renderings("direct-tdpa", k_o=1000.0, sim_rate_hz=20.0)
    assert (one.variant, two.variant) == ("one-port", "two-port")
    assert math.isinf(one.passivity_max_damping or 0.0)
    cells = [Cell(r, 1000.0, 20.0, 100.0, hand, TAP) for r in (DIRECT, one, two)]
    m = cell_metrics(simulate(cells), cells)
    assert m[0].energy_out_mj > 1.0  # delayed direct rendering pushes the user
    assert m[2].energy_out_mj < 0.1 * m[0].energy_out_mj
    assert m[2].stable


def test_every_peer_sweeps_tunings_the_local_models_do_not() -> None:
    for s in SCHEMES:
        if s.startswith("local"):
            with pytest.raises(ValueError, match="local model"):
                peer_renderings(s, k_o=300.0, sim_rate_hz=20.0)
            continue
        rs = peer_renderings(s, k_o=300.0, sim_rate_hz=20.0)
        assert all(r.scheme == s for r in rs)
        assert len({r.variant for r in rs}) == len(rs)
    assert len(peer_renderings("virtual-coupling", k_o=300.0, sim_rate_hz=20.0)) == 2  # tools
    with pytest.raises(ValueError, match="k_o"):
        peer_renderings("mmt", k_o=-1.0, sim_rate_hz=20.0)


def test_quantisation_and_jitter_are_what_the_servo_reads() -> None:
    r = Rendering("mmt", "mmt", k_h=1000.0, b_h=5.0)
    cell = Cell(r, 300.0, 20.0, 0.0, DEFAULT_HAND, IMPACT)
    q = 23e-6
    run = simulate([cell], options=RunOptions(quantum_m=q))
    steps = run.x[0] / q
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    a = simulate([cell], options=RunOptions(jitter_s=300e-6, seed=1))
    b = simulate([cell], options=RunOptions(jitter_s=300e-6, seed=1))
    c = simulate([cell])
    np.testing.assert_array_equal(a.x, b.x)  # the seed draws the jitter
    assert 1e-7 < np.abs(a.x - c.x).max() < 1e-3  # it moves the probe, by a little
    assert cell_metrics(a, [cell])[0].stable
    with pytest.raises(ValueError, match="jitter"):
        RunOptions(jitter_s=2e-3)
    with pytest.raises(ValueError, match="quantum"):
        RunOptions(quantum_m=math.nan)


def test_felt_windows_hold_whole_cycles_of_every_rate() -> None:
    for hz in (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 30.0):
        w = felt_window_s(hz)
        half = w / 2.0
        assert abs(hz * half - round(hz * half)) < 1e-6  # whole probe cycles in each half
        assert abs(half / 0.1 - round(half / 0.1)) < 1e-6  # whole periods of 10 Hz and up
    assert felt_window_s(30.0) == pytest.approx(0.4)
    with pytest.raises(ValueError):
        felt_window_s(0.0)


def test_absurd_object_models_are_refused() -> None:
    with pytest.raises(ValueError, match="absurd"):
        ObjectModel("x", stiffness_error=0.0)
    with pytest.raises(ValueError, match="absurd"):
        ObjectModel("x", "sls", relax_ratio=1.0, relax_time_s=0.0)
    with pytest.raises(ValueError, match="absurd"):
        replace(STIFFENING, stiffening_m=math.nan)


BAND = (0.5, 1.0, 2.0, 4.0, 8.0)  # the felt band the ranking judges (Hz)


def _product(
    mode: str,
    k_o: float,
    rate: float,
    delay_ms: float,
    *,
    reached: ObjectModel | None = None,
    planes: bool = True,
    identified: tuple[str, ...] = (),
    ahead: ObjectModel | None = None,
    plane_check_s: float = 0.0,
    rest_plane: bool = False,
    also: tuple[float, ...] = (),
    **key_changes,
) -> Rendering:
    """The product's rendering of ``mode`` for K_o, as the benchmark renders it (the client's key,
    its table cell scaled to K_o, its gains following the K_o reported through the cells
    designed, the verified plane of each where the own-response check verifies the K_o
    reported, and of the cells the objects ``identified`` (named) are identified at), with
    ``key_changes`` applied to the key; with ``reached``, every cell that object reaches is
    designed too (``--design-reached``); without ``planes``, no verified plane; with ``ahead``,
    the planes of the cells that object reaches undesigned, checked alone (ahead, as the client
    checks them); ``plane_check_s``: each plane renders that long after its cell verifies.
    Without ``rest_plane`` (the default here: these tests are of the designs and verified planes
    through the simulation, a client with another user near), never the rest plane. ``also``:
    more K_o [N/m] whose cells the table has designed (the benchmark's grid shares one key
    across its K_o)."""
    kind = "pi" if mode == "local-pi" else "p"
    key = replace(_gain_key(kind, rate, delay_ms, DeviceModel()), **key_changes)
    ks = [k_o] if reached is None else _k_o_designed(reached, k_o, True)
    ks += [k for k in also if k not in ks]
    designs = {(kind, key, k): _design_cell(key, k) for k in ks}
    design = designs[(kind, key, k_o)].at(k_o)
    found = {w: _plane_cell(w[1], w[2], d) for w, d in designs.items()} if planes else {}
    if planes:
        jobs = _identified_plane_jobs(designs, identified, [k_o])
        found.update({w: _plane_cell(*job) for w, job in jobs.items()})
    if planes and ahead is not None:
        alone = _alone_plane_jobs(designs, [ahead.name], [k_o])
        found.update({w: _checked_plane_cell(*job) for w, job in alone.items()})
    return rendering_for(
        mode, sim_rate_hz=rate, design=design, table=_table(designs, kind, key),
        planes=_planes(found, kind, key), plane_check_s=plane_check_s, rest_plane=rest_plane,
    )  # fmt: skip


def _box_stable(r: Rendering, obj: ObjectModel, k_o: float, rate: float, delay_ms: float) -> bool:
    hands = (*DEFAULT_HAND_BOX.corners(), DEFAULT_HAND)
    cells = [Cell(r, k_o, rate, delay_ms, h, tr, obj) for h in hands for tr in (PRESS, TAP, IMPACT)]
    return all(m.stable for m in cell_metrics(simulate(cells), cells))


@pytest.mark.slow
@pytest.mark.parametrize(("rate", "delay_ms"), [(20.0, 0.0), (20.0, 100.0)])
def test_on_the_spring_the_verified_plane_is_felt_as_the_object_with_every_hand_stable(
    rate: float, delay_ms: float
) -> None:
    # the design for an object up to 25 % off is felt up to 0.2 (ln) off the spring over the
    # band; once the client's own-response check has seen the object yield as reported, the
    # verified plane renders: felt within the stiffness JND at every frequency, every hand
    # of the box stable through the switch
    k = 300.0
    product, design_only = (
        _product("local-pi", k, rate, delay_ms, planes=p) for p in (True, False)
    )
    assert product.planes and not design_only.planes
    assert _box_stable(product, SPRING, k, rate, delay_ms)
    errs = [abs(math.log(abs(_felt(product, SPRING, k, rate, delay_ms, hz)))) for hz in BAND]
    assert max(errs) < math.log(1.1)
    before = [abs(math.log(abs(_felt(design_only, SPRING, k, rate, delay_ms, hz)))) for hz in BAND]
    assert max(before) > 1.5 * max(errs)
    # without the plane of the stiffness it identifies, an object 20 % softer than reported is
    # rendered with the design, as before
    for hz in (1.0, 8.0):
        q, q0 = (_felt(r, SPRING_SOFTER, k, rate, delay_ms, hz) for r in (product, design_only))
        assert q == pytest.approx(q0, rel=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("obj", [SPRING_SOFTER, SPRING_STIFFER], ids=lambda o: o.name)
def test_an_object_whose_k_o_is_reported_wrong_is_felt_as_itself_once_identified(
    obj: ObjectModel,
) -> None:
    # the K_o reported is 25 % too high / 17 % too low: the design made for it is felt 0.2-0.5
    # off the object (ln); once the own-response check has identified the object's stiffness,
    # the plane of that stiffness's cell renders, felt within the JND with every hand stable
    k, rate, delay_ms = 300.0, 20.0, 100.0
    product = _product("local-pi", k, rate, delay_ms, identified=(obj.name,))
    design_only = _product("local-pi", k, rate, delay_ms, planes=False)
    assert _box_stable(product, obj, k, rate, delay_ms)
    errs = [abs(math.log(abs(_felt(product, obj, k, rate, delay_ms, hz)))) for hz in BAND]
    before = [abs(math.log(abs(_felt(design_only, obj, k, rate, delay_ms, hz)))) for hz in BAND]
    assert max(errs) < math.log(1.1) < max(before)


@pytest.mark.slow
def test_a_rendering_that_changes_once_while_held_is_read_on_the_longer_probe() -> None:
    # 1000 N/m reported on a spring 20 % stiffer, 20 Hz, 200 ms each way: the own-response check
    # identifies the object during the felt probe's ramp, and the capped plane of its stiffness,
    # checked on arrival (not ahead), arrives 2 s later, 3.2 s into the press, while the probe is held still. The force settles
    # through the 400 ms round trip after the change, which the standard probe cannot tell from
    # a limit cycle; on the longer probe the change is over before the hold ends, and the plane
    # is read: felt about as the device's stiffness (1000 of 1200 N/m), steadily
    k, rate, delay_ms = 1000.0, 20.0, 200.0
    product = _product(
        "local-pi",
        k,
        rate,
        delay_ms,
        identified=("spring-1.2",),
        plane_check_s=PRODUCT_PLANE_CHECK_S,
    )
    depth = felt_depth_m(k, FMAX, SPRING_STIFFER)
    cells = [
        Cell(product, k, rate, delay_ms, None, felt_trajectory(1.0, depth, longer=longer),
             SPRING_STIFFER)
        for longer in (False, True)
    ]  # fmt: skip
    short, longer = (felt_response(simulate([c]), [c])[0] for c in cells)
    assert short is None
    assert longer is not None and 0.75 < abs(longer) < 0.95


def test_where_the_design_is_felt_closer_than_the_plane_it_stays() -> None:
    # 1000 N/m, 20 Hz, no delay: at the top of the cell the cell's design is felt 0.02 off the
    # spring over the band, its verified plane (with the 1.5 N*s/m damper it needs) 0.05: the
    # product has no plane there; on 300 N/m the plane needs no damper and renders
    assert not _product("local-pi", 1000.0, 20.0, 0.0).planes
    assert _product("local-pi", 300.0, 20.0, 0.0).planes


@pytest.mark.slow
def test_the_product_holds_an_object_a_fifth_stiffer_than_reported() -> None:
    # designed for the K_o reported alone, the local model rang with a heavy, lightly
    # damped hand on an object 20 % stiffer (300 N/m, 20 Hz, no delay); the design now holds on
    # one up to 25 % stiffer than the top of its cell, every hand of the box, every trajectory
    k, rate = 300.0, 20.0
    assert _box_stable(_product("local-p", k, rate, 0.0), SPRING_STIFFER, k, rate, 0.0)
    naive = _product("local-p", k, rate, 0.0, stiffer_by=0.0)
    assert not _box_stable(naive, SPRING_STIFFER, k, rate, 0.0)


@pytest.mark.slow
def test_the_product_holds_the_viscoelastic_object_with_the_b_o_reported() -> None:
    # over one 50 ms tick the viscoelastic object with mass is 1.7 times stiffer than its K_o;
    # designed for B_o = 0 the local model's own-force compensation overshoots and some hand of
    # the box rings (300 N/m, 20 Hz, no delay); designed with the B_o the simulation reports, as
    # the client designs for the World's B_o, every hand on every trajectory is stable
    k, rate = 300.0, 20.0
    b_o = math.floor(SLS.reported_b_o(k, rate))
    assert b_o > 150
    assert _box_stable(_product("local-p", k, rate, 0.0, b_o=float(b_o)), SLS, k, rate, 0.0)
    assert not _box_stable(_product("local-p", k, rate, 0.0), SLS, k, rate, 0.0)


@pytest.mark.slow
def test_the_product_holds_the_viscoelastic_object_where_it_stays_stiff_for_many_ticks() -> None:
    # at 100 Hz the viscoelastic object is K_o + B_o = 2.6 K_o stiff over its first tick and
    # stays near 2 K_o through its 0.1 s relaxation (10 ticks), where eq. 9 relaxes within two:
    # the P design checked up to 1.25 K_o (300 N/m, 2 ticks of delay) held the heavy, loosely
    # held hand (0.6 kg, 20 N/m, 2 N*s/m) in a 4.5 Hz, 0.75 mm ring after a tap. Checked up to
    # the one-tick stiffness of its cell, every hand of the box holds on every trajectory
    k, rate, delay_ms = 300.0, 100.0, 10.0
    b_o = float(math.floor(SLS.reported_b_o(k, rate)))
    assert b_o > 1.25 * k
    product = _product("local-p", k, rate, delay_ms, b_o=b_o)
    assert _box_stable(product, SLS, k, rate, delay_ms)


@pytest.mark.slow
def test_the_viscoelastic_object_is_felt_as_it_yields_not_as_a_softer_spring() -> None:
    # the design is judged against the object the simulation reports, eq. 9's K_o + B_o (1 -
    # z^-1), stiffer to a quick press than at rest: judged against K_o alone it was felt 0.80
    # off the viscoelastic object (ln; its gains made softer to cancel the stiffening), further
    # than a plane of the K_o reported (0.41). Now within 0.25, every hand of the box stable
    k, rate = 300.0, 20.0
    b_o = float(math.floor(SLS.reported_b_o(k, rate)))
    product = _product("local-p", k, rate, 0.0, b_o=b_o)
    wall = peer_renderings("static-local", k_o=k, sim_rate_hz=rate)[1]
    err, wall_err = (
        max(abs(math.log(abs(_felt(r, SLS, k, rate, 0.0, hz)))) for hz in BAND)
        for r in (product, wall)
    )
    assert err < 0.25 < wall_err
    assert _box_stable(product, SLS, k, rate, 0.0)


@pytest.mark.slow  # a benchmark run over the capped plane's cells
def test_above_the_device_stiffness_the_product_renders_a_flat_plane() -> None:
    # at 3000 N/m (three times the device's stiffness) the paper's PI creeps toward K_o at
    # 0.5 Hz and is soft at 4 Hz; the product renders the plane at the rest surface with the
    # device's stiffness, felt as a third of K_o all over the band
    k, rate = 3000.0, 20.0
    r = _product("local-pi", k, rate, 0.0)
    assert r.k_h == pytest.approx(1000.0) and r.own_gain * k == pytest.approx(1.0, rel=0.01)
    q = [abs(_felt(r, SPRING, k, rate, 0.0, hz)) for hz in (0.5, 2.0, 8.0)]
    assert max(q) < 0.45 and min(q) > 0.3
    paper = _product("local-pi", k, rate, 0.0, own_force=False)
    q_paper = [abs(_felt(paper, SPRING, k, rate, 0.0, hz)) for hz in (0.5, 2.0, 8.0)]
    assert max(q_paper) / min(q_paper) > 1.5  # what the plane replaces: a stiffness that drifts
    assert min(q_paper) < min(q)


def _fake_design(
    cell: int, k_h: float, i_gain: float, b_h: float, own: float, scale_max: float,
    hold: ProxyHold = "foh",
) -> GainDesign:  # fmt: skip
    g = GainTable().grid_point(cell)  # a cell's design is made for its grid point
    return GainDesign(
        k_h=k_h, i_gain=i_gain, b_h=b_h, proxy_hold=hold, worst_spectral_radius=0.9,
        rho_limit=0.95, felt_stiffness_ratio_1hz=1.0, felt_stiffness_ratio_8hz=1.0, k_o=g,
        k_o_range=(0.85 * g, 1.4 * g), rate_ratio=20, delay_ticks=0, mode="pi",
        own_gain=own, scale_max=scale_max,
    )  # fmt: skip


def test_the_local_models_gains_follow_the_k_o_reported_as_the_clients_gain_table_gives_them() -> (
    None
):
    # the 1-D run looks each reported K_o up as the client does: a designed cell scaled to it,
    # else the nearest designed cell below (C_h keeping its share of K_o, no integral more than
    # two cells below), or with none below the nearest above scaled down
    key = _gain_key("pi", 20.0, 0.0, DeviceModel())
    table = GainTable()
    cells = {48: _fake_design(48, 90.0, 900.0, 0.5, 0.011, 1.08),
             52: _fake_design(52, 135.0, 0.0, 2.0, 0.0074, 1.0, "zoh"),
             59: _fake_design(59, 270.0, 2700.0, 5.0, 0.0036, 1.1)}  # fmt: skip
    for c, d in cells.items():
        table.store(key, c, d)
    rows = tuple(TableCell.from_design(c, d, table.grid_ratio) for c, d in cells.items())
    k = np.geomspace(40.0, 2000.0, 400)
    *got, foh = TableGains([rows] * len(k)).gains_and_hold(k)
    for j, kj in enumerate(k):
        want = table.lookup(key, float(kj)) or table.fallback(key, float(kj))
        assert want is not None
        expect = (want.k_h, want.i_gain, want.b_h, want.own_gain)
        assert [float(g[j]) for g in got] == pytest.approx(expect, rel=1e-9), kj
        # and each patch is rendered with the hold its design was checked with
        assert bool(foh[j]) == (want.proxy_hold == "foh"), kj
    assert not foh.all() and foh.any()


def test_on_the_stiffening_object_the_product_renders_its_clients_fallback_and_holds() -> None:
    # a heavy, stiff, lightly damped hand tapping the stiffening object (100 N/m, 50 Hz, 100 ms)
    # as it stiffens to 2.7 K_o. The earlier benchmark scaled the 100 N/m design's K_h with the
    # K_o reported and kept its 0.5 N*s/m damper, a rendering the client never makes: the hold
    # rang at the 0.5 mm limit. With only its first cell designed, the client renders that cell's
    # own gains beyond it (its C_h keeping its share of K_o), and every hand of the box holds
    k, rate, delay = 100.0, 50.0, 100.0
    r = _product("local-p", k, rate, delay)
    assert _box_stable(r, STIFFENING, k, rate, delay)
    k_h, _, _, own = TableGains([r.table]).gains(np.array([2.7 * k]))
    assert k_h[0] < 1.1 * r.k_h
    assert own[0] * 2.7 * k == pytest.approx(r.own_gain * k, rel=0.1)


@pytest.mark.slow
def test_a_press_held_in_the_fallback_past_a_cell_boundary_holds_still() -> None:
    # the stiffening object reported at 1000 N/m, 20 Hz, no delay, only its first cell designed:
    # a press held 4.6 mm in leaves the object's surface where the K_o reported (about 1400 N/m)
    # sits on a cell boundary. With the fallback's C_h stepping from cell to cell the held force
    # rang at 5 Hz, 0.045 N peak to peak, and no felt response could be read; with C_h keeping
    # its share of the K_o reported itself, the force is still and the response is read
    k, rate = 1000.0, 20.0
    r = _product("local-pi", k, rate, 0.0)
    cell = Cell(
        r, k, rate, 0.0, None, felt_trajectory(1.0, felt_depth_m(k, FMAX, STIFFENING)), STIFFENING
    )
    run = simulate([cell])
    held = (run.t >= 1.5) & (run.t < cell.trajectory.sine_start_s)
    assert float(np.ptp(run.f[0][held])) < 0.005
    assert felt_response(run, [cell])[0] is not None


def test_the_benchmark_hands_gains_over_in_the_clients_time() -> None:
    from haptic_collab.client.app import GAIN_TRANSFER_S

    assert PRODUCT_GAIN_TRANSFER_S == GAIN_TRANSFER_S
    r = _product("local-p", 100.0, 20.0, 0.0)
    assert r.gain_transfer_s == GAIN_TRANSFER_S


@pytest.mark.slow
def test_pressing_through_the_stiffening_objects_cells_changes_gains_without_a_jolt() -> None:
    # with every cell the object reaches designed, a 10 mm press crosses about ten of them, each
    # design with its own K_h, damper, C_h and proxy hold. The client hands each over in 0.25 s
    # (a transfer force, and the change of C_h sliding in); the benchmark switched them at
    # once, and the press, probe as a position source, stepped the force by 0.48 N in one tick.
    # Rendered as the client renders it, the largest step in one tick is 0.07 N (the designs
    # alone: their verified planes, the tangent in each cell, would render from the check's
    # verdict on, and hand over with smaller steps)
    k, rate = 100.0, 20.0
    r = _product("local-p", k, rate, 0.0, reached=STIFFENING, planes=False)
    holds = {c.proxy_hold for c in r.table}
    assert len(r.table) > 5 and holds == {"zoh", "foh"}

    def largest_step_n(rendering: Rendering) -> float:
        run = simulate([Cell(rendering, k, rate, 0.0, None, PRESS, STIFFENING)])
        return float(np.max(np.abs(np.diff(run.f[0]))))

    assert largest_step_n(r) < 0.1
    assert largest_step_n(replace(r, gain_transfer_s=0.0)) > 0.3


@pytest.mark.slow
def test_the_product_follows_the_reported_stiffness_into_a_stiffening_object() -> None:
    # with the cells the stiffening object reaches designed (a client that has pressed there),
    # each switched in at once, the local model feels the object's tangent stiffness at 0.5-1 Hz,
    # as MMT does; with only the first K_o's cell, the client renders the nearest designed cell's
    # gains while it designs the next, and a press feels about half the object
    k, rate = 300.0, 20.0
    full = _product("local-p", k, rate, 0.0, reached=STIFFENING)
    assert len(full.table) > 5
    at_once = replace(full, gain_transfer_s=0.0)
    for hz in (0.5, 1.0):
        assert abs(_felt(at_once, STIFFENING, k, rate, 0.0, hz)) == pytest.approx(1.0, abs=0.05)
    first = _product("local-p", k, rate, 0.0)
    assert abs(_felt(first, STIFFENING, k, rate, 0.0, 1.0)) < 0.6


@pytest.mark.slow
def test_handed_over_as_the_client_does_the_designed_cells_feel_the_stiffening_object() -> None:
    # a press held where the reported K_o sits on the boundary of cells 64 and 65 (first-order
    # holds, K_h 372 and 427 N/m, C_h K_h = 1 both) chattered between their designs, 1.82-1.98
    # N about a 1.95 N hold, with no steady felt response: the first-order hold's slide carried
    # the change of C_h on top of the K_h step's transfer force. Handed over as the client now does, the
    # designed cells feel the object's tangent stiffness
    k, rate = 300.0, 20.0
    full = _product("local-p", k, rate, 0.0, reached=STIFFENING)
    for hz in (0.5, 1.0):
        assert abs(_felt(full, STIFFENING, k, rate, 0.0, hz)) == pytest.approx(1.0, abs=0.05)


@pytest.mark.slow
def test_neighbouring_cells_of_mixed_holds_hold_every_hand_of_the_box() -> None:
    # at 300 N/m, 50 Hz, no delay, the cells a press into the stiffening object crosses mix zero-
    # and first-order holds with K_h from 67 to 934 N/m (C_h K_h = 1 each): handed over with the
    # first-order hold's slide carrying the change of C_h, the four stiff grips of the box rang at
    # 3.7-12.7 mm; each design alone was stable. Every hand on every trajectory now settles
    k, rate = 300.0, 50.0
    r = _product("local-p", k, rate, 0.0, reached=STIFFENING)
    assert {c.proxy_hold for c in r.table} == {"zoh", "foh"}
    assert max(c.k_h for c in r.table) > 5 * min(c.k_h for c in r.table)
    assert _box_stable(r, STIFFENING, k, rate, 0.0)


@pytest.mark.slow
@pytest.mark.parametrize(("rate", "delay_ms"), [(20.0, 0.0), (50.0, 100.0)])
def test_with_each_cells_plane_checked_ahead_a_press_feels_the_stiffening_object(
    rate: float, delay_ms: float
) -> None:
    # the stiffening object at 300 N/m, only its first cell designed (the default run). With the
    # fallback between the cells a press is felt 0.46-0.74 off the object (ln, over the band).
    # With the plane of each cell the press reaches checked ahead, as the client checks the
    # cells around the K_o reported in the background, each renders as soon as the own-response
    # check verifies the tangent there: felt within 0.1 of the object at every frequency of the
    # band, and every hand of the box holds. Checked on arrival instead, each new cell rendered
    # the fallback for the check's 2 s and the press hunted between cells for 6-8 s
    k = 300.0
    ahead = _product("local-pi", k, rate, delay_ms, ahead=STIFFENING)
    fallback = _product("local-pi", k, rate, delay_ms)
    assert len(ahead.planes) > len(fallback.planes) + 5
    assert _box_stable(ahead, STIFFENING, k, rate, delay_ms)
    errs = [abs(math.log(abs(_felt(ahead, STIFFENING, k, rate, delay_ms, hz)))) for hz in BAND]
    before = [abs(math.log(abs(_felt(fallback, STIFFENING, k, rate, delay_ms, hz)))) for hz in BAND]
    assert max(errs) < 0.1 and max(before) > 4 * max(errs)


@pytest.mark.slow
@pytest.mark.parametrize(("rate", "delay_ms"), [(50.0, 50.0), (100.0, 50.0)])
def test_alone_a_press_into_the_stiffening_object_crosses_the_planes_with_every_hand_stable(
    rate: float, delay_ms: float
) -> None:
    # the user alone: the rest plane (K_h the tangent K_o reported) until the own-response check
    # verifies a cell's plane, the rest plane again HOLD_BACK_S after the last one; each change
    # slid off over the transfer time. Every hand of the box on every trajectory is stable. (On
    # the benchmark's full grid, crossing back whenever no verified plane rendered left one
    # condition without box-stability, 100 N/m at 100 Hz with 50 ms, `local-p`:
    # `haptic bench fidelity --rest-hold-back-s 0`; an earlier switch without the slide rang at
    # 7 Hz, 8 mm, at 50 Hz.)
    k = 100.0
    product = _product(
        "local-p", k, rate, delay_ms, ahead=STIFFENING, rest_plane=True, also=(300.0, 1000.0)
    )
    assert product.rest_plane and product.planes and product.rest_hold_back_s > 0.0
    assert _box_stable(product, STIFFENING, k, rate, delay_ms)
    # and the press does reach verified planes: rendered without them it is felt otherwise
    bare = replace(product, planes=())
    q, q0 = (_felt(r, STIFFENING, k, rate, delay_ms, 1.0) for r in (product, bare))
    assert abs(q - q0) > 0.01 * abs(q0)


@pytest.mark.slow
def test_alone_the_viscoelastic_object_is_felt_closer_through_the_rest_plane() -> None:
    # the design through the simulation, 200 ms each way, is felt 1.25 (ln) off the viscoelastic
    # object at 300 N/m and 20 Hz (the benchmark's felt error); alone, the rest plane with the
    # damper eq. 9's B_o asks for is felt 0.41 off, and every hand of the box is stable on it
    k, rate, delay_ms = 300.0, 20.0, 200.0
    b_o = float(math.floor(SLS.reported_b_o(k, rate)))
    alone = _product("local-p", k, rate, delay_ms, b_o=b_o, rest_plane=True)
    near = _product("local-p", k, rate, delay_ms, b_o=b_o)
    assert _box_stable(alone, SLS, k, rate, delay_ms)
    err = [abs(math.log(abs(_felt(alone, SLS, k, rate, delay_ms, hz)))) for hz in BAND]
    err_near = [abs(math.log(abs(_felt(near, SLS, k, rate, delay_ms, hz)))) for hz in BAND]
    assert max(err) < max(err_near) - math.log(1.1)
