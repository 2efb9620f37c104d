"""The gain policy's one function (shared.gains.choose): which gains render for a patch, and why.

Pure and table-driven: the designs here are stored by hand (:func:`known_gains`), so each rule is
seen alone, without a design run. What a user would notice: forces stay off until gains verified
for the contact render; a user alone feels the object's rest plane at once; more delay than the
gains in use were made for never keeps those gains; the server's gains render only where this
device can render them.
"""

from __future__ import annotations

import copy
import math
import random
from dataclasses import replace

import pytest

from haptic_collab.shared.felt_stiffness import felt_stiffness
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
from haptic_collab.shared.gains.choose import (
    PLANE_ALONE,
    VERIFIED_SOURCES,
    CheckJob,
    Contact,
    DesignJob,
    Known,
    Options,
    PlaneJob,
    choose,
    known_gains,
    static_felt_stiffness,
    without_design,
)
from haptic_collab.shared.gains.interim import interim_design
from haptic_collab.shared.gains.key import GainKey, make_gain_key
from haptic_collab.shared.gains.policy import FALLBACK_K_RATIO
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.local_model_update import GainChoice, LocalModelUpdate, SurfacePatch
from haptic_collab.shared.protocol import Patch, PlaneModel, RecommendedGains, parse_server
from tests.support.sessions import press_patch

K_O = 300.0
OPTIONS = Options(servo_rate_hz=1000.0, sim_rate_hz=20.0, k_h_max=1000.0, b_h_max=10.0)
REST = PlaneModel(point=(0.0, 0.0, 0.1), normal=(0.0, 0.0, 1.0))


def _key(delay_ticks: int = 0, stiff_ratio: float = 1.0) -> GainKey:
    return make_gain_key(
        servo_rate_hz=1000.0, sim_rate_hz=20.0, delay_ticks=delay_ticks, mode="pi", margin=0.15,
        k_h_max=1000.0, b_h_max=10.0, b_o=0.0, stiff_ratio=stiff_ratio,
    )  # fmt: skip


def _surface(
    tick: int = 1,
    k_o: float = K_O,
    *,
    rest: bool = False,
    gains: RecommendedGains | None = None,
    force_n: float = 1.0,
) -> tuple[SurfacePatch, RecommendedGains | None]:
    msg = parse_server(
        press_patch(tick, force_n, k_o, k_o=k_o, rest_plane=REST if rest else None, gains=gains)
    )
    assert isinstance(msg, Patch)
    return SurfacePatch.from_wire(msg), msg.gains


def _gains(k_h: float, i_gain: float = 0.0, delay_ticks: int = 0, k_o: float = K_O):
    return known_gains(
        k_h, i_gain, 2.0, "zoh", k_o_eff=k_o, rate_ratio=50, delay_ticks=delay_ticks,
        spectral_radius=0.9, felt_1hz=0.95,
    )  # fmt: skip


def _known(table: GainTable | None = None, interim=None, planes=None) -> Known:
    return Known(table or GainTable(), dict(interim or {}), dict(planes or {}))


def _in_use(k_h: float, delay_ticks: int, k_o: float = K_O) -> LocalModelUpdate:
    surface, _ = _surface(k_o=k_o)
    return LocalModelUpdate.from_surface(
        surface, k_h=k_h, i_gain=3000.0, b_h=2.0, hold_ticks=50,
        choice=GainChoice(delay_ticks=delay_ticks, spectral_radius=0.9),
    )  # fmt: skip


def test_a_first_contact_with_nothing_verified_waits_with_forces_off_and_asks_for_work() -> None:
    surface, rec = _surface()
    key = _key()
    choice = choose(surface, rec, Contact(key), _known(), OPTIONS)
    assert choice.source is None and choice.gains is None  # nothing renders: forces stay off
    assert DesignJob(key, K_O) in choice.jobs
    cell = GainTable().cell(K_O)
    assert [j for j in choice.jobs if isinstance(j, CheckJob)] == [CheckJob(key, cell, ())]


def test_the_cells_design_renders_verified_and_asks_for_nothing() -> None:
    key = _key()
    table = GainTable()
    table.store(key, table.cell(K_O), _gains(250.0, 3000.0))
    surface, rec = _surface()
    choice = choose(surface, rec, Contact(key), _known(table), OPTIONS)
    assert choice.source == "design" and choice.verified and not choice.fallback
    assert choice.gains is not None and choice.gains.k_h == pytest.approx(250.0)
    assert choice.jobs == ()


def test_alone_the_rest_plane_renders_at_once_unless_turned_off() -> None:
    key = _key()
    surface, rec = _surface(rest=True)
    choice = choose(surface, rec, Contact(key), _known(), OPTIONS)
    assert choice.source == "rest" and choice.verified and choice.rest is not None
    assert choice.rest.k_h == K_O  # the object's own stiffness, within the device's
    assert DesignJob(key, K_O) in choice.jobs  # for when another user joins
    off = Options(**{**OPTIONS.__dict__, "rest_plane": False})
    assert choose(surface, rec, Contact(key), _known(), off).source is None


def test_more_delay_than_the_gains_in_use_were_made_for_renders_the_fallback() -> None:
    # in contact on 1 tick-of-delay gains; the loop now has 3 ticks and nothing is known for it
    key = _key(delay_ticks=3)
    surface, rec = _surface()
    choice = choose(surface, rec, Contact(key, in_use=_in_use(250.0, 1)), _known(), OPTIONS)
    assert choice.source == "fallback" and not choice.verified
    assert choice.gains is not None
    assert choice.gains.k_h <= FALLBACK_K_RATIO * K_O + 1e-9 and choice.gains.i_gain == 0.0
    assert any(isinstance(j, CheckJob) for j in choice.jobs)
    # the same delay as the gains in use: they stay (unverified) while the check runs
    same = choose(surface, rec, Contact(_key(1), in_use=_in_use(250.0, 1)), _known(), OPTIONS)
    assert same.source == "in-use" and same.gains is not None and same.gains.k_h == 250.0


def test_checked_interim_gains_render_verified_even_for_a_first_contact() -> None:
    key = _key()
    table = GainTable()
    cell = table.cell(K_O)
    surface, rec = _surface()
    known = _known(table, interim={(key, cell): _gains(60.0)})
    choice = choose(surface, rec, Contact(key), known, OPTIONS)
    assert choice.source == "interim" and choice.verified and choice.fallback
    assert choice.jobs == (DesignJob(key, K_O),)  # the design is still to come


def test_a_wider_coupling_class_covers_a_narrower_one() -> None:
    key = _key(stiff_ratio=math.sqrt(2.0))
    table = GainTable()
    table.store(_key(stiff_ratio=2.0), table.cell(K_O), _gains(200.0))
    surface, rec = _surface()
    choice = choose(surface, rec, Contact(key), _known(table), OPTIONS)
    assert choice.source == "covering" and choice.verified


@pytest.mark.parametrize(
    ("k_h", "b_h", "delay_ticks", "renders"),
    [
        (250.0, 2.0, 2, True),
        (1500.0, 2.0, 2, False),
        (250.0, 20.0, 2, False),
        (250.0, 2.0, 1, False),
    ],
)
def test_the_servers_gains_render_only_within_this_device_and_delay(
    k_h: float, b_h: float, delay_ticks: int, renders: bool
) -> None:
    rec_in = RecommendedGains(
        k_h=k_h, i_gain=0.0, b_h=b_h, proxy_hold="zoh", theta_m=0.0, delay_ticks=delay_ticks,
        interim=False, own_gain=0.0,
    )  # fmt: skip
    surface, rec = _surface(gains=rec_in)
    choice = choose(surface, rec, Contact(_key(delay_ticks=2)), _known(), OPTIONS)
    assert (choice.source == "server") is renders
    if renders:
        assert choice.gains is not None and choice.gains.k_h == k_h
    local = Options(**{**OPTIONS.__dict__, "gains": "local"})
    assert choose(surface, rec, Contact(_key(delay_ticks=2)), _known(), local).source is None


def test_an_object_as_reported_asks_for_its_plane_and_renders_it_once_checked() -> None:
    key = _key()
    table = GainTable()
    cell = table.cell(K_O)
    table.store(key, cell, _gains(250.0, 3000.0))
    surface, rec = _surface()
    asked = choose(surface, rec, Contact(key, own_response=True), _known(table), OPTIONS)
    assert asked.source == "design" and PlaneJob(key, cell, cell) in asked.jobs
    plane = _gains(K_O)
    known = _known(table, planes={(key, cell, cell): plane})
    checked = choose(surface, rec, Contact(key, own_response=True), known, OPTIONS)
    assert checked.source == "plane" and checked.plane_tick == surface.tick
    assert checked.gains is not None and checked.gains.k_h == pytest.approx(K_O)
    # in a cell with no design, the plane checked alone renders meanwhile
    alone = _known(planes={(key, cell, PLANE_ALONE): plane})
    assert choose(surface, rec, Contact(key, own_response=True), alone, OPTIONS).source == "plane"


def test_choose_is_pure_total_and_the_server_recommends_only_what_it_verified() -> None:
    """Random contacts: the same inputs give the same choice, nothing known is changed, a choice
    never renders unverified gains with nothing in use, and the server's rule
    (:func:`without_design`) agrees with the client's where no design exists."""
    rng = random.Random(58)
    table = GainTable()
    for c in range(10, 40, 3):
        table.store(_key(), c, _gains(0.8 * table.grid_point(c), k_o=table.grid_point(c)))
    interim = {(_key(1), c): _gains(0.3 * table.grid_point(c)) for c in range(20, 30)}
    for _ in range(300):
        k_o = math.exp(rng.uniform(math.log(20.0), math.log(5000.0)))
        key = _key(rng.randint(0, 3), rng.choice([1.0, math.sqrt(2.0), 2.0]))
        in_use = (
            _in_use(rng.uniform(10.0, 900.0), rng.randint(0, 3)) if rng.random() < 0.5 else None
        )
        known = _known(table, interim=interim)
        before = copy.deepcopy((dict(known.interim), dict(known.planes), table.cells()))
        surface, rec = _surface(rng.randint(1, 99), k_o, rest=rng.random() < 0.2)
        contact = Contact(key, in_use=in_use)
        choice = choose(surface, rec, contact, known, OPTIONS)
        assert choice == choose(surface, rec, contact, known, OPTIONS)
        assert (dict(known.interim), dict(known.planes), table.cells()) == before
        if in_use is None:
            assert choice.source is None or choice.source in VERIFIED_SOURCES
        if choice.source is not None and choice.source != "rest":
            assert choice.gains is not None and 0.0 < choice.gains.k_h
        if table.lookup(key, k_o) is None and not surface.rest_plane:
            gains, source, _ = without_design(key, k_o, known, in_use, OPTIONS.rate_ratio)
            if in_use is not None or source in VERIFIED_SOURCES:
                assert source == choice.source and gains == choice.gains
            else:  # unverified gains (the nearest cell) never render for a first contact
                assert choice.source is None


def _interim_in_use(key: GainKey, k_h: float, own_gain: float = 0.0) -> LocalModelUpdate:
    surface, _ = _surface()
    return LocalModelUpdate.from_surface(
        surface, k_h=k_h, i_gain=0.0, b_h=2.0, hold_ticks=50, own_gain=own_gain,
        choice=GainChoice(delay_ticks=key.delay_ticks, spectral_radius=0.9, source="interim"),
    )  # fmt: skip


def test_a_design_arriving_in_a_hold_does_not_step_the_felt_stiffness() -> None:
    """Interim gains without compensation (felt about K_o / 5) render in a press; the cell's
    design (compensated: felt K_o) arrives: the press keeps the interim gains; the next contact,
    or another cell, gets the design. A design felt within a JND of the interim gains renders."""
    key = _key(delay_ticks=6)
    table = GainTable()
    cell = table.cell(K_O)
    soft = _gains(0.25 * K_O)
    interim = {(key, cell): soft}
    design = replace(_gains(200.0), own_gain=1.0 / 200.0)  # C_h K_h = 1: felt K_o
    table.store(key, cell, design)
    known = _known(table, interim=interim)
    in_use = _interim_in_use(key, soft.k_h)
    surface, rec = _surface()
    held = choose(surface, rec, Contact(key, in_use=in_use, in_use_key=(key, cell)), known, OPTIONS)
    assert held.held and held.source == "interim" and held.gains == soft
    assert static_felt_stiffness(soft.k_h, 0.0, 0.0, K_O) == pytest.approx(K_O / 5)
    # released: the design renders
    out, _ = _surface(force_n=0.0)
    free = choose(replace(out, in_contact=False), rec, Contact(key, in_use=in_use,
                  in_use_key=(key, cell)), known, OPTIONS)  # fmt: skip
    assert free.source == "design" and not free.held
    # the key changed (the gains in use were chosen for another cell): the design renders
    other = choose(surface, rec, Contact(key, in_use=in_use, in_use_key=(key, cell + 1)),
                   known, OPTIONS)  # fmt: skip
    assert other.source == "design"
    # interim gains felt like the design (compensated): nothing to hold
    alike = _interim_in_use(key, 0.25 * K_O, own_gain=1.0 / (0.25 * K_O))
    assert choose(surface, rec, Contact(key, in_use=alike, in_use_key=(key, cell)), known,
                  OPTIONS).source == "design"  # fmt: skip


def test_a_wider_class_s_uncompensated_design_renders_only_while_a_compensated_check_runs() -> None:
    # the palpation demo's slide: A's coupled key (class sqrt 2) had no design of its own, and the
    # class-2 design covering it was the paper's PI (no own-force compensation), which a sliding
    # hand feels softer than the object: over the lump A felt +10 % where the solid has +20 %
    key = _key(stiff_ratio=math.sqrt(2.0))
    table = GainTable()
    cell = table.cell(K_O)
    paper_pi = _gains(100.0, 700.0)
    table.store(_key(stiff_ratio=2.0), cell, paper_pi)
    surface, rec = _surface()
    choice = choose(surface, rec, Contact(key), _known(table), OPTIONS)
    assert choice.source == "covering" and choice.verified  # verified: it renders meanwhile
    checks = [j for j in choice.jobs if isinstance(j, CheckJob)]
    assert checks == [CheckJob(key, cell, ())]  # and a check for this key is asked
    # the check, as the link and the server's worker run it, finds compensated gains
    job = checks[0]
    found = interim_design(
        job.key, job.cell, table.grid_ratio, DEFAULT_HAND_BOX, job.candidates,
        design_fallback=False,
    )  # fmt: skip
    assert found.i_gain == 0.0 and found.own_gain * found.k_h == pytest.approx(1.0)
    felt = {
        name: float(
            felt_stiffness(
                1.0, k_o=K_O, k_h=g.k_h, i_gain=g.i_gain, b_h=g.b_h, proxy_hold=g.proxy_hold,
                own_gain=g.own_gain,
            )[0]
        )
        / K_O
        for name, g in (("paper", paper_pi), ("found", found))
    }  # fmt: skip
    # a hand moving at 1 Hz feels the object through the compensated gains, softer through the PI
    assert abs(math.log(felt["found"])) < math.log(1.1) < abs(math.log(felt["paper"]))
    # once checked, they render instead of the covering design
    known = _known(table, interim={(key, cell): found})
    again = choose(surface, rec, Contact(key), known, OPTIONS)
    assert again.source == "interim" and again.gains is not None
    assert again.gains.own_gain == found.own_gain
    # a covering design that compensates its own force needs no check: it is felt as the object
    table2 = GainTable()
    table2.store(_key(stiff_ratio=2.0), cell, replace(_gains(200.0), own_gain=1.0 / 200.0))
    plain = choose(surface, rec, Contact(key), _known(table2), OPTIONS)
    assert plain.source == "covering"
    assert not [j for j in plain.jobs if isinstance(j, CheckJob)]
