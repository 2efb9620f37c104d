"""A gain table as a file (shared.gains.table_file): what a session loads renders the same gains,
and a file of other design code, another hand box or a broken record is refused whole."""

from __future__ import annotations

import ast
import copy
import json
import math

import pytest

from haptic_collab.shared.full_loop import HandBox
from haptic_collab.shared.gains.key import make_gain_key
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.table_file import (
    CONSTANTS_MODULE,
    _constants_read,
    _module_ast,
    _without_docstrings,
    design_code_hash,
    design_code_modules,
    key_from_record,
    key_record,
    load_shipped,
    load_table_document,
    table_document,
)


def _key(stiff_ratio: float = 1.0):
    return make_gain_key(
        servo_rate_hz=1000.0,
        sim_rate_hz=100.0,
        delay_ticks=0,
        mode="p",
        margin=0.15,
        k_h_max=1000.0,
        b_h_max=10.0,
        b_o=0.0,
        stiff_ratio=stiff_ratio,
    )


@pytest.fixture(scope="module")
def designed() -> GainTable:
    table = GainTable()
    table.design(_key(), 300.0)
    return table


def test_a_loaded_table_renders_the_same_gains_at_every_reported_stiffness(designed) -> None:
    doc = json.loads(json.dumps(table_document(designed, "code")))  # through JSON text
    fresh = GainTable()
    assert load_table_document(fresh, doc, "code") == 1
    for k_o in (285.0, 300.0, 310.0):
        assert fresh.lookup(_key(), k_o) == designed.lookup(_key(), k_o)
    # loading again adds nothing and keeps what is there
    assert load_table_document(fresh, doc, "code") == 0


def test_keys_round_trip_including_a_rigid_coupling_class() -> None:
    for ratio in (1.0, math.sqrt(2.0), math.inf):
        rec = json.loads(json.dumps(key_record(_key(ratio))))
        assert key_from_record(rec) == _key(ratio)


def test_a_file_of_other_code_hand_box_or_grid_is_refused(designed) -> None:
    doc = table_document(designed, "code")
    with pytest.raises(ValueError, match="design code"):
        load_table_document(GainTable(), doc, "other")
    with pytest.raises(ValueError, match="hand box"):
        load_table_document(GainTable(HandBox(mass_kg=(0.2, 0.6))), doc, "code")
    with pytest.raises(ValueError, match="grid ratio"):
        load_table_document(GainTable(grid_ratio=1.2), doc, "code")
    with pytest.raises(ValueError, match="format"):
        load_table_document(GainTable(), {**doc, "format": 99}, "code")


@pytest.mark.parametrize(
    "field, value",
    [("worst_spectral_radius", 1.02), ("k_h", float("nan")), ("b_h", -1.0), ("proxy_hold", "x")],
)
def test_a_record_that_is_not_a_stable_design_is_refused_and_nothing_is_stored(
    designed, field, value
) -> None:
    doc = copy.deepcopy(table_document(designed, "code"))
    good = copy.deepcopy(doc["cells"][0])
    good["cell"] += 1  # a second, valid cell before the broken one
    doc["cells"].insert(0, good)
    doc["cells"][1]["design"][field] = value
    table = GainTable()
    with pytest.raises(ValueError):
        load_table_document(table, doc, "code")
    assert len(table) == 0


def test_malformed_documents_are_refused_with_a_value_error(designed) -> None:
    doc = table_document(designed, "code")
    for bad in (
        [],
        {**doc, "cells": "x"},
        {**doc, "cells": [1]},
        {**doc, "cells": [{**doc["cells"][0], "cell": "3"}]},
        {**doc, "cells": [{**doc["cells"][0], "key": {"mode": "p"}}]},
    ):
        with pytest.raises(ValueError):
            load_table_document(GainTable(), bad, "code")


def test_the_design_code_hash_ignores_docstrings_but_not_code() -> None:
    a = ast.parse('def f(x):\n    "doc one"\n    return x + 1\n')
    b = ast.parse('def f(x):\n    """doc two, longer"""\n    # a comment\n    return x + 1\n')
    c = ast.parse('def f(x):\n    "doc one"\n    return x + 2\n')
    dump = [ast.dump(_without_docstrings(t)) for t in (a, b, c)]
    assert dump[0] == dump[1] != dump[2]
    mods = design_code_modules()
    assert "haptic_collab.shared.gains.search" in mods and "haptic_collab.shared.full_loop" in mods
    assert "haptic_collab.shared.gains.table_file" not in mods  # its format is not the designs'
    assert len(design_code_hash()) == 16


def test_a_policy_constant_the_design_does_not_read_leaves_the_hash_alone() -> None:
    """Of shared.gains.policy only what the design reads is hashed: a new value of the choice's
    fallback ratio keeps every shipped table; one of the design's tie or decay margin does not."""
    mods = design_code_modules()
    assert CONSTANTS_MODULE in mods

    def hashed_with(name: str, value: float) -> str:
        tree = _without_docstrings(_module_ast(CONSTANTS_MODULE))
        for node in tree.body:
            target = getattr(node, "target", None) or (getattr(node, "targets", None) or [None])[0]
            if isinstance(target, ast.Name) and target.id == name:
                node.value = ast.Constant(value)  # type: ignore[attr-defined]
        return ast.dump(_constants_read(tree, mods))

    base = ast.dump(_constants_read(_without_docstrings(_module_ast(CONSTANTS_MODULE)), mods))
    assert hashed_with("FALLBACK_K_RATIO", 0.2) == base
    assert hashed_with("HOLD_BACK_S", 2.0) == base
    assert hashed_with("DESIGN_TIE", 0.01) != base
    assert hashed_with("MIN_DECAY_RATE_PER_S", 2.0) != base
    # a name a read constant is made of is read too
    assert hashed_with("MAX_STIFF_RATIO_CLASS", 64.0) != base


def test_every_shipped_table_is_of_this_design_code_and_loads() -> None:
    table = GainTable()
    loaded = load_shipped(table)
    # a refused file says why (a string); a shipped table must be fresh for this code
    assert loaded and all(isinstance(n, int) and n > 0 for n in loaded.values()), loaded
    for key, _, design in table.cells():
        assert design.worst_spectral_radius < 1.0 and design.k_h <= key.k_h_max
        assert design.b_h <= key.b_h_max and design.delay_ticks == key.delay_ticks
        assert design.mode == key.mode or key.mode == "pi"  # PI may fall back to P
