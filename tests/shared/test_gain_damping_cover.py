"""A FEM solid's keys (object damping B_o > 0) rendered from the shipped gain tables.

The shipped tables hold designs for B_o = 0; each design says up to which B_o it passed its own
check on the damped loop (``b_o_covered``, shared.gains.damping_cover, checked offline). What a
user would notice: a press on a damped object whose B_o the shipped design covers renders that
design from the first patch, with no design or check run during the session (so it does not
depend on the machine's load), and the server recommends the same gains; a key above the
coverage waits for its own design as before; a corrupted coverage in a table file is refused.
The designs rendered are re-checked here on a lattice of hands finer than the design's hand box,
on the damped loop, with the full-loop check functions (not the file's number).
"""

from __future__ import annotations

import ast
import json
import math
from dataclasses import replace
from typing import Any

import pytest

from haptic_collab.server.gains import GainAdvisor
from haptic_collab.shared.gains.choose import (
    CheckJob,
    Contact,
    DesignJob,
    Known,
    Options,
    choose,
    table_design,
)
from haptic_collab.shared.gains.damping_cover import covered_b_o, damped_check
from haptic_collab.shared.gains.key import GainKey, covering_classes, make_gain_key
from haptic_collab.shared.gains.policy import B_O_COVER_LATTICE
from haptic_collab.shared.gains.table import GainTable, cell_k_o_range
from haptic_collab.shared.gains.table_file import (
    CONSTANTS_MODULE,
    COVER_ROOTS,
    _constants_read,
    _module_ast,
    _without_docstrings,
    b_o_covered,
    cover_code_hash,
    design_code_hash,
    design_code_modules,
    key_from_record,
    load_shipped,
    load_table_document,
    table_document,
)
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.protocol import DeviceInfo, Hello, Patch, parse_server
from tests.support.hand_lattice import lattice, worst_on_lattice
from tests.support.sessions import press_patch, welcomed_session

PHANTOM = DeviceInfo(
    profile="phantom-desktop",
    max_force_n=7.9,
    max_stiffness_n_per_m=1000.0,
    max_damping_n_s_per_m=10.0,
)
OPTIONS = Options(servo_rate_hz=1000.0, sim_rate_hz=20.0, k_h_max=1000.0, b_h_max=10.0)

#: FEM-like keys whose shipped design for B_o = 0 covers their B_o (phantom-desktop's table,
#: docs/results/fem-table-cover-2026-11-27.json): (B_o [N/m], K_o [N/m], delay ticks, coupling
#: class).
COVERED = [
    (7.7, 220.0, 0, 1.0),  # the liver sphere's top
    (40.0, 220.0, 0, 1.0),
    (7.5, 200.0, 3, 1.0),  # covered to 8 N/m: a B_o below 8 renders it
    (15.5, 200.0, 3, math.sqrt(2.0)),  # covered to 16 N/m
    (7.5, 9.2, 0, 1.0),  # a soft spot below the grid's 50 N/m of before (shipped down to 5 N/m)
]
#: Keys of the same kind the coverage of their own class does not reach (the compensated designs
#: there sit at the decay margin, and a few N/m of B_o slow their slowest ring below 1/s): their
#: design is asked for during the session, as before, and meanwhile a wider coupling class's
#: design renders where its coverage reaches the key's B_o (``covering``), else nothing (a first
#: contact waits). (B_o, K_o, delay, class, the source of the first patch.) With classes up to 16
#: shipped, a wider class's softer design covers 40 N/m at 3 ticks too; beyond the lattice's 64
#: N/m no design is covered.
ABOVE = [
    (8.0, 200.0, 0, 1.0, "covering"),
    (40.0, 200.0, 0, 1.0, "covering"),
    (40.0, 200.0, 3, 1.0, "covering"),
    (70.0, 200.0, 3, 1.0, None),
    # the FEM stress bowl's rim in liver (K_o 9.2, B_o 24.6 N/m): its own class is covered to
    # 8 N/m; before the grid reached below 50 N/m it rendered fallback gains while designed
    (24.6, 9.2, 0, 1.0, "covering"),
    (24.6, 9.2, 1, 1.0, "covering"),
]


@pytest.fixture(scope="module")
def shipped() -> GainTable:
    table = GainTable()
    loaded = load_shipped(table)
    assert all(isinstance(n, int) and n > 0 for n in loaded.values()), loaded
    return table


def _key(mode: str, b_o: float, delay_ticks: int, stiff_ratio: float = 1.0) -> GainKey:
    return make_gain_key(
        servo_rate_hz=1000.0, sim_rate_hz=20.0, delay_ticks=delay_ticks, mode=mode, margin=0.15,
        k_h_max=1000.0, b_h_max=10.0, b_o=b_o, stiff_ratio=stiff_ratio,
    )  # fmt: skip


def _surface(k_o: float, b_o: float) -> SurfacePatch:
    msg = parse_server(press_patch(1, 1.0, k_o, k_o=k_o, b_o=b_o))
    assert isinstance(msg, Patch)
    return SurfacePatch.from_wire(msg)


@pytest.mark.parametrize("mode", ["p", "pi"])
@pytest.mark.parametrize(("b_o", "k_o", "delay", "sr"), COVERED)
def test_a_covered_fem_key_renders_the_shipped_design_from_first_contact_without_a_job(
    shipped: GainTable, mode: str, b_o: float, k_o: float, delay: int, sr: float
) -> None:
    key = _key(mode, b_o, delay, sr)
    choice = choose(_surface(k_o, b_o), None, Contact(key), Known(shipped, {}, {}), OPTIONS)
    undamped = shipped.lookup(replace(key, b_o=0.0), k_o)
    assert undamped is not None
    # the first patch renders a designed, verified cell: no waiting, no fallback, no work asked
    assert choice.source == "design-b_o" and choice.verified and not choice.fallback
    assert choice.gains == undamped and choice.jobs == ()


@pytest.mark.parametrize("mode", ["p", "pi"])
@pytest.mark.parametrize(("b_o", "k_o", "delay", "sr", "source"), ABOVE)
def test_a_key_above_the_coverage_still_asks_for_its_design(
    shipped: GainTable, mode: str, b_o: float, k_o: float, delay: int, sr: float, source: str | None
) -> None:
    key = _key(mode, b_o, delay, sr)
    undamped = replace(key, b_o=0.0)
    assert shipped.lookup(undamped, k_o) is not None  # the shipped cell is there, but
    assert b_o_covered(shipped, undamped, shipped.cell(k_o)) < b_o  # its check did not reach
    choice = choose(_surface(k_o, b_o), None, Contact(key), Known(shipped, {}, {}), OPTIONS)
    assert choice.source == source and DesignJob(key, k_o) in choice.jobs
    if source is None:  # a first contact waits with forces off while its gains are checked
        assert choice.gains is None
        assert any(isinstance(j, CheckJob) and j.key == key for j in choice.jobs)
    else:  # the narrowest wider coupling class's design within its own damping coverage
        wider = [
            replace(key, stiff_ratio=c)
            for c in covering_classes(key.stiff_ratio)
            if table_design(shipped, replace(key, stiff_ratio=c), k_o)[1] == "design-b_o"
        ]
        assert wider and table_design(shipped, wider[0], k_o) == (choice.gains, "design-b_o")


@pytest.mark.slow
@pytest.mark.parametrize(("b_o", "k_o", "delay", "sr"), COVERED)
def test_the_design_rendered_is_stable_on_the_damped_loop_for_a_finer_lattice_of_hands(
    shipped: GainTable, b_o: float, k_o: float, delay: int, sr: float
) -> None:
    # 6 x 6 x 6 hands over the box (the design saw 5 x 3 x 5), every sampling tick, K_o' over
    # the damped key's range, the gains as rendered at the reported K_o and at the cell's top
    key = _key("pi", b_o, delay, sr)
    design, source = table_design(shipped, key, k_o)
    assert design is not None and source == "design-b_o"
    cell = shipped.cell(k_o)
    lo, hi = cell_k_o_range(key, cell, shipped.grid_ratio)
    hands = lattice(6)
    for served in (design, design.at(0.999 * shipped.grid_point(cell + 1))):
        k_os = [served.k_o_range[0], math.sqrt(served.k_o_range[0] * hi), hi]
        for b in (0.5 * b_o, b_o, math.floor(b_o) + 0.999):  # up to the key's whole N/m
            rho, where = worst_on_lattice(
                served, k_os, sim_rate_hz=20.0, delay_ticks=delay, hands=hands, b_o=b
            )
            assert rho < 1.0, (b, where)


def test_the_server_recommends_the_covered_design_as_a_design_not_interim_gains() -> None:
    adv = GainAdvisor(20.0)
    hello = Hello(protocol=1, role="user", name="A", device=PHANTOM, local_model="pi")
    b_o, k_o, _, _ = COVERED[1]
    g = adv.recommend("u1", hello, k_o_eff=k_o, k_o_stiff=k_o, b_o=b_o)
    assert g is not None and not g.interim
    assert adv.take_jobs() == []  # nothing designed or checked for it
    d = adv.table.lookup(replace(_key("pi", b_o, 0), b_o=0.0), k_o)
    assert d is not None and (g.k_h, g.own_gain, g.b_h) == (d.k_h, d.own_gain, d.b_h)


def test_a_client_session_renders_it_from_its_first_patch(shipped: GainTable) -> None:
    b_o, k_o, _, _ = COVERED[1]
    s = welcomed_session(
        "A", "u1", b_h_max=10.0, mode="pi", gains="local", rest_plane=False, gain_table=shipped
    )
    update = s.receive(press_patch(1, 1.0, k_o, k_o=k_o, b_o=b_o), 0.05)
    assert update is not None and update.choice is not None
    assert update.choice.source == "design-b_o" and not update.choice.fallback
    assert s.design_wanted is None and s.interim_wanted is None


def test_the_shipped_coverage_is_fresh_and_on_the_lattice() -> None:
    for name in ("phantom-desktop", "touch"):
        doc = _shipped_doc(name)
        assert doc["damping_cover"] == {"code": cover_code_hash(), "lattice": [*B_O_COVER_LATTICE]}
        values = {rec["b_o_covered"] for rec in doc["cells"]}
        assert values <= {0.0, *B_O_COVER_LATTICE}


def _shipped_doc(name: str) -> dict[str, Any]:
    from haptic_collab.cli.shipped_tables import shipped_dir

    return json.loads((shipped_dir() / f"{name}.json").read_text("utf-8"))


def _small_doc() -> dict[str, Any]:
    doc = _shipped_doc("phantom-desktop")
    doc["cells"] = [r for r in doc["cells"] if r["b_o_covered"] > 0.0][:3]
    return doc


@pytest.mark.parametrize("bad", [math.nan, -1.0, math.inf, "8", True, None])
def test_a_corrupted_coverage_in_a_table_file_is_refused_and_nothing_is_stored(bad: Any) -> None:
    doc = _small_doc()
    doc["cells"][1]["b_o_covered"] = bad
    text = json.dumps(doc)  # as written to a file: NaN and Infinity are JSON's extensions
    table = GainTable()
    with pytest.raises(ValueError, match="b_o_covered"):
        load_table_document(table, json.loads(text), design_code_hash())
    assert len(table) == 0


def test_a_coverage_of_another_check_code_is_dropped_and_the_designs_kept() -> None:
    doc = _small_doc()
    doc["damping_cover"] = {"code": "0" * 16, "lattice": [1.0]}
    table = GainTable()
    assert load_table_document(table, doc, design_code_hash()) == 3
    assert all(b_o_covered(table, k, c) == 0.0 for k, c, _ in table.cells())


def test_a_table_written_and_read_again_keeps_its_coverage() -> None:
    doc = _small_doc()
    table = GainTable()
    load_table_document(table, doc, design_code_hash())
    again = GainTable()
    load_table_document(again, table_document(table, design_code_hash()), design_code_hash())
    want = {(json.dumps(r["key"]), r["cell"]): r["b_o_covered"] for r in doc["cells"]}
    from haptic_collab.shared.gains.table_file import key_record

    got = {(json.dumps(key_record(k)), c): b_o_covered(again, k, c) for k, c, _ in again.cells()}
    assert got == want and all(v > 0.0 for v in got.values())


@pytest.mark.slow
def test_the_coverage_is_the_check_s_own_answer_for_a_shipped_design(shipped: GainTable) -> None:
    # one design recomputed, where the coverage stops inside the lattice: every lattice point
    # up to it passes the check, the next one fails it
    b_o, k_o, delay, _, _ = ABOVE[0]
    key = _key("p", 0.0, delay)
    cell = shipped.cell(k_o)
    design = shipped.lookup(key, shipped.grid_point(cell))
    assert design is not None
    got = covered_b_o(key, cell, design, shipped.grid_ratio, shipped.hand_box)
    assert 0.0 < got == b_o_covered(shipped, key, cell) < b_o
    nxt = min(b for b in B_O_COVER_LATTICE if b > got)
    assert not damped_check(key, cell, design, nxt, shipped.grid_ratio, shipped.hand_box)[0]


def test_the_lattice_and_the_check_are_the_cover_code_s_not_the_design_code_s() -> None:
    # a new lattice or check asks for the coverage again (tools.codegen --check), never for the
    # 2808 designs: the design code's hash does not read them
    tree = _without_docstrings(_module_ast(CONSTANTS_MODULE))

    def constants(modules: tuple[str, ...]) -> set[str]:
        kept = _constants_read(tree, modules).body
        return {t.id for n in kept if isinstance(n, ast.AnnAssign | ast.Assign) for t in
                (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}  # fmt: skip

    cover_mods, design_mods = design_code_modules(COVER_ROOTS), design_code_modules()
    assert "B_O_COVER_LATTICE" in constants(cover_mods)
    assert "B_O_COVER_LATTICE" not in constants(design_mods)
    assert "haptic_collab.shared.gains.interim" in cover_mods
    assert "haptic_collab.shared.gains.damping_cover" not in design_mods


def test_a_b_o_above_the_coverage_by_less_than_the_key_s_step_is_not_rendered_from_it(
    shipped: GainTable,
) -> None:
    """The key floors B_o to whole N/m: an object of 8.5 N/m has a key of 8, and a design checked
    up to 8 N/m (and failing between 8 and 16) must not render for it; one of 7.5 N/m may."""
    k_o, delay = 200.0, 3
    undamped = _key("p", 0.0, delay)
    assert b_o_covered(shipped, undamped, shipped.cell(k_o)) == 8.0
    assert table_design(shipped, _key("p", 7.5, delay), k_o)[1] == "design-b_o"
    assert table_design(shipped, _key("p", 8.5, delay), k_o) == (None, None)
    assert table_design(shipped, _key("p", 8.0, delay), k_o) == (None, None)


def test_a_design_stored_over_the_checked_one_has_no_coverage(shipped: GainTable) -> None:
    """A coverage belongs to the design that was checked: a table holding another design for the
    cell (a build or a cache made elsewhere) does not render it for a damped key."""
    table = GainTable()
    load_shipped(table)
    k_o, key = 220.0, _key("p", 0.0, 0)
    cell = table.cell(k_o)
    assert b_o_covered(table, key, cell) == 64.0
    before = table_design(table, _key("p", 40.0, 0), k_o)
    assert before[1] == "design-b_o"
    other = replace(before[0], k_h=0.9 * before[0].k_h)  # not the design that was checked
    table.store(key, cell, other)
    assert b_o_covered(table, key, cell) == 0.0
    assert table_design(table, _key("p", 40.0, 0), k_o) == (None, None)
    # and a table written out again does not carry the old design's coverage to the new one:
    # the new design is left for the next coverage pass to check
    doc = table_document(table, design_code_hash())
    (rec,) = (c for c in doc["cells"] if c["cell"] == cell and key_from_record(c["key"]) == key)
    assert "b_o_covered" not in rec
    from tools.codegen.gain_tables import stale_cover

    assert stale_cover(doc) == "damping coverage missing on 1 cells"


def test_a_contact_rendering_a_covered_design_asks_its_coupled_class_checked_ahead(
    shipped: GainTable,
) -> None:
    """A contact that renders a shipped design with no job (here the damping coverage's) still
    gets checked ahead of need where it is likely to go next, as after a design of its own: a
    second user's arrival then finds the coupled class checked, not the quarter-K_o fallback.
    Asked once per key and cell, and nothing for keys the table already has."""
    b_o, k_o, _, _ = COVERED[1]
    s = welcomed_session(
        "B", "u2", b_h_max=10.0, mode="pi", gains="local", rest_plane=False, gain_table=shipped
    )
    update = s.receive(press_patch(1, 1.0, k_o, k_o=k_o, b_o=b_o), 0.05)
    assert update is not None and update.choice is not None
    assert update.choice.source == "design-b_o"
    asked = [(k, c) for k, c, _ in s.checks_ahead]
    key = _key("pi", b_o, 0)
    cell = shipped.cell(k_o)
    # the coupled class of this cell is not covered for this B_o: it is asked first
    coupled = replace(key, stiff_ratio=2.0)
    assert table_design(shipped, coupled, k_o)[0] is None
    assert asked[0] == (coupled, cell)
    # nothing the table already renders, and the gains in use as the first candidate
    assert all(
        table_design(shipped, k, shipped.grid_point(c) * 1.0001)[0] is None for k, c in asked
    )
    rendering = table_design(shipped, key, k_o)[0]
    assert all(cands == (rendering,) for _, _, cands in s.checks_ahead)
    s.checks_ahead.clear()
    s.receive(press_patch(2, 1.0, k_o, k_o=k_o, b_o=b_o), 0.10)
    assert s.checks_ahead == []  # the same key and cell: asked once


def test_a_balloon_contact_on_the_shipped_grid_asks_nothing_ahead(shipped: GainTable) -> None:
    s = welcomed_session(
        "B", "u2", b_h_max=10.0, mode="pi", gains="local", rest_plane=False, gain_table=shipped
    )
    update = s.receive(press_patch(1, 1.0, 300.0, k_o=300.0), 0.05)
    assert update is not None and update.choice is not None
    assert update.choice.source == "design"
    # every key likely next at 0 ticks, class 1 (class 2, a tick more, the cells around) is in
    # the shipped tables: nothing to check
    assert s.checks_ahead == []
