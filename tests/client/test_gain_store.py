"""A client's table starts from the shipped tables and this machine's cache of designs, and adds
its own designs to the cache (client.gain_store)."""

from __future__ import annotations

import json
import logging

import pytest

from haptic_collab.client.gain_store import cache_path, load_cache, preload, save_cache
from haptic_collab.shared.gains.key import make_gain_key
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.table_file import design_code_hash


def _key(delay: int):
    return make_gain_key(
        servo_rate_hz=1000.0,
        sim_rate_hz=100.0,
        delay_ticks=delay,
        mode="p",
        margin=0.15,
        k_h_max=1000.0,
        b_h_max=10.0,
        b_o=0.0,
        stiff_ratio=1.0,
    )


@pytest.fixture(scope="module")
def designs() -> GainTable:
    """Two designed cells (delay 0 and 1), made once for the module."""
    table = GainTable()
    table.design(_key(0), 300.0)
    table.design(_key(1), 300.0)
    return table


def _table(designs: GainTable, *delays: int) -> GainTable:
    """A new table with the designs of ``delays`` (as if this session had made them)."""
    out = GainTable()
    for key, cell, design in designs.cells():
        if key.delay_ticks in delays:
            out.store(key, cell, design)
    return out


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("HAPTIC_GAIN_CACHE", str(tmp_path))
    return tmp_path


def test_a_design_made_in_one_session_is_there_at_the_next_sessions_first_patch(
    cache_dir, designs
) -> None:
    code = design_code_hash()
    first = _table(designs, 0)
    expected = first.lookup(_key(0), 300.0)
    assert expected is not None
    assert save_cache(first, code) == 1
    second = GainTable()
    info = preload(second)
    assert info["cached"] == 1 and info["design_code"] == code
    assert second.lookup(_key(0), 300.0) == expected  # no design to wait for


def test_two_clients_writing_the_cache_keep_both_designs(cache_dir, designs) -> None:
    code = design_code_hash()
    a, b = _table(designs, 0), _table(designs, 1)
    save_cache(a, code)
    assert save_cache(b, code) == 2
    merged = GainTable()
    assert load_cache(merged, code) == 2


def test_a_broken_cache_is_ignored_with_a_warning_and_written_anew(
    cache_dir, caplog, designs
) -> None:
    code = design_code_hash()
    cache_path(code).write_text("{not json")
    table = GainTable()
    with caplog.at_level(logging.WARNING):
        assert load_cache(table, code) == 0
    assert "not used" in caplog.text and len(table) == 0
    table = _table(designs, 0)
    assert save_cache(table, code) == 1
    assert json.loads(cache_path(code).read_text())["design_code"] == code


def test_a_cache_of_other_design_code_is_not_read(cache_dir, designs) -> None:
    table = _table(designs, 0)
    save_cache(table, "0123456789abcdef")
    assert load_cache(GainTable(), design_code_hash()) == 0
    assert preload(GainTable(), cache=True)["cached"] == 0


def test_an_unwritable_cache_does_not_stop_the_client(tmp_path, monkeypatch, designs) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("HAPTIC_GAIN_CACHE", str(blocker / "sub"))  # under a file: cannot exist
    assert save_cache(_table(designs, 0), design_code_hash()) == -1


def test_a_built_in_device_is_covered_and_a_custom_one_is_built_into_the_cache(
    cache_dir, capsys
) -> None:
    """The Phantom Desktop's shipped table holds every cell of the grid at 20 Hz; a device of
    other limits holds none until ``haptic gains-table --cache`` builds its cells, which the
    next session's table then starts with."""
    from haptic_collab.cli import main
    from haptic_collab.client.gain_store import device_coverage

    def coverage(k_h_max: float, b_h_max: float) -> tuple[int, int]:
        table = GainTable()
        preload(table)
        return device_coverage(
            table, k_h_max=k_h_max, b_h_max=b_h_max, mode="pi", servo_rate_hz=1000.0,
            sim_rate_hz=20.0,
        )  # fmt: skip

    held, of = coverage(1000.0, 10.0)
    assert of > 0 and held == of
    assert coverage(1500.0, 8.0) == (0, of)
    assert device_coverage(GainTable(), k_h_max=1000.0, b_h_max=10.0, mode="p",
                           servo_rate_hz=1000.0, sim_rate_hz=50.0)[1] == 0  # fmt: skip
    argv = ["gains-table", "--cache", "--max-stiffness", "1500", "--max-damping", "8"]
    assert main([*argv, "--max-jobs", "2", "--workers", "1"]) == 0
    assert "2 cells designed now" in capsys.readouterr().out
    assert coverage(1500.0, 8.0) == (2, of)  # and the next run goes on from there


# (K_o_eff, K_o_stiff) [N/m] of the patches of one contact, as the stress meshes' demo at 50 ms
# (2 ticks of delay) measured them (docs/real-objects.md): the torus's resting user B while A's
# press coupled it (class 2 sqrt 2), then uncoupled again with its class held; the bowl's A as
# its press coupled it ever more (classes 8 and 16), then uncoupled.
STRESS_CONTACTS = {
    "torus B": [(1202.9, 1202.9), (859.4, 2003.6), (859.4, 2003.6), (1202.9, 1202.9)],
    "bowl A": [(307.3, 307.3), (175.9, 1178.2), (169.1, 1362.7), (155.3, 1895.7),
               (169.1, 1362.7), (175.9, 1178.2), (306.1, 306.1)],
}  # fmt: skip


@pytest.mark.parametrize("profile", ["phantom-desktop", "touch"])
@pytest.mark.parametrize("mode", ["p", "pi"])
@pytest.mark.parametrize("contact", sorted(STRESS_CONTACTS))
def test_a_contact_coupled_beyond_class_2_renders_shipped_designs_throughout(
    cache_dir, profile, mode, contact
) -> None:
    """Coupling classes up to 16 are in the shipped grid: each patch of a contact whose coupling
    rises to them, and falls again with its class held, renders a shipped design at once, with
    no design, check or fallback asked. Before, the torus's B rendered the nearest cell's gains
    unverified, then interim gains, and the bowl's A the quarter-K_o fallback."""
    from dataclasses import replace

    from haptic_collab.client.devices.profiles import get_sim_profile
    from haptic_collab.shared.gains.choose import Contact, Known, Options, choose
    from haptic_collab.shared.gains.key import held_stiff_ratio
    from haptic_collab.shared.local_model_update import SurfacePatch
    from haptic_collab.shared.protocol import Patch, parse_server
    from tests.support.sessions import press_patch

    lim = get_sim_profile(profile).limits
    table = GainTable()
    preload(table, cache=False)
    known = Known(table, {}, {})
    options = Options(
        servo_rate_hz=1000.0, sim_rate_hz=20.0, k_h_max=lim.max_stiffness_n_per_m,
        b_h_max=lim.max_damping_n_s_per_m, mode=mode, rest_plane=False,
    )  # fmt: skip
    cls, sources = 1.0, []
    for tick, (k_eff, k_stiff) in enumerate(STRESS_CONTACTS[contact], start=1):
        msg = parse_server(press_patch(tick, 0.5, k_eff, k_o=k_eff))
        assert isinstance(msg, Patch)
        surface = replace(SurfacePatch.from_wire(msg), k_o_stiff=k_stiff)
        cls = held_stiff_ratio(cls, k_eff, k_stiff)
        key = make_gain_key(
            servo_rate_hz=1000.0, sim_rate_hz=20.0, delay_ticks=2, mode=mode, margin=0.15,
            k_h_max=options.k_h_max, b_h_max=options.b_h_max, b_o=0.0, stiff_ratio=cls,
        )  # fmt: skip
        choice = choose(surface, None, Contact(key), known, options)
        sources.append((cls, choice.source, choice.jobs))
        assert choice.gains is not None and choice.gains.worst_spectral_radius < 1.0
    assert max(c for c, _, _ in sources) > 2.0  # the contact left the former grid
    assert all(s == "design" and not jobs for _, s, jobs in sources), sources
