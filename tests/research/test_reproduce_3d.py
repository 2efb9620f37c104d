"""Fig. 10-11 on the 3-D balloon: the product's world, servo and simulated hand, run in-process."""

from __future__ import annotations

import json
import pathlib
from typing import Any

import pytest

from haptic_collab.research.press_3d import (
    K_O_TARGET,
    STABLE_HOLD_P2P_MM,
    Timeline3D,
    product_cases,
    stiff_balloon,
)
from haptic_collab.research.reproduce_3d import reproduce_3d

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: A shortened press: 0.3 s approach, 0.7 s press, 1.5 s hold (2.5 s per case).
SHORT = Timeline3D(hold_s=1.5)

CASE_FIELDS = {
    "k_h_n_per_m",
    "k_o_n_per_m",
    "steady_state_error_mm",
    "sim_loop_stable",
    "full_loop_stable",
    "full_loop_spectral_radius",
    "hold_p2p_mm",
    "hand",
}


@pytest.fixture(scope="module")
def figs(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[pathlib.Path, dict[str, dict[str, Any]]]:
    out = tmp_path_factory.mktemp("fig3d") / "out"
    return out, reproduce_3d("all", out, timeline=SHORT, product=False)


def test_the_balloon_is_stiffened_to_the_papers_k_o() -> None:
    stiff = stiff_balloon()
    assert stiff.k_o == pytest.approx(K_O_TARGET, rel=0.10)
    assert 250.0 < stiff.k_o_unscaled < 350.0  # the default balloon's top (README: about 310)
    assert stiff.scale == pytest.approx(stiff.k_o / stiff.k_o_unscaled, rel=1e-6)


def test_files_and_fields(figs: tuple[pathlib.Path, dict[str, dict[str, Any]]]) -> None:
    out, res = figs
    assert set(res) == {"fig10", "fig11"}
    for name in ("fig10", "fig11"):
        assert (out / f"{name}.png").read_bytes()[:8] == PNG_MAGIC
        assert json.loads((out / f"{name}.json").read_text()) == res[name]
        assert res[name]["note"] and "paper" in res[name]["note"]
        for case in res[name]["cases"].values():
            assert set(case) >= CASE_FIELDS
            assert case["k_o_n_per_m"] == pytest.approx(K_O_TARGET, rel=0.10)
            assert case["hand"]["as_felt_by_the_probe"]["mass_kg"] == pytest.approx(0.495)
    assert set(res["fig10"]["cases"]) == {"kh600", "kh700"}
    assert set(res["fig11"]["cases"]) == {"kh1200"}


def test_soft_local_models_hold_and_the_stiff_one_oscillates(
    figs: tuple[pathlib.Path, dict[str, dict[str, Any]]],
) -> None:
    _, res = figs
    kh600, kh700 = (res["fig10"]["cases"][k] for k in ("kh600", "kh700"))
    kh1200 = res["fig11"]["cases"]["kh1200"]
    # the paper's simulation-loop verdicts (eq. 8: K_h < K_o)
    assert kh600["sim_loop_stable"] and kh700["sim_loop_stable"]
    assert not kh1200["sim_loop_stable"]
    # what a user feels: K_h = 600 holds still about 10 mm in, K_h = 1200 shakes the hand
    assert kh600["hold_p2p_mm"] < STABLE_HOLD_P2P_MM
    assert kh600["probe_depth_mm"] == pytest.approx(10.0, abs=1.5)
    assert kh1200["hold_p2p_mm"] > max(1.0, 10.0 * kh600["hold_p2p_mm"])
    # P leaves a steady-state error e = F / K_h; the stiffer model leaves less (eq. 11)
    assert kh700["steady_state_error_mm"] < kh600["steady_state_error_mm"]
    assert kh600["steady_state_error_mm"] == pytest.approx(
        kh600["force_n"] / kh600["k_h_n_per_m"] * 1000.0, rel=0.05
    )
    # the full loop with the hand is judged for every case, by its spectral radius
    for case in (kh600, kh700, kh1200):
        assert case["full_loop_stable"] == (case["full_loop_spectral_radius"] < 1.0)
    assert not kh1200["full_loop_stable"]


def test_product_cases_are_skipped_with_a_note_without_the_design(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import importlib

    real = importlib.import_module

    def missing(name: str, *args: Any, **kwargs: Any) -> Any:
        if name == "haptic_collab.shared.gains.design":
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(importlib, "import_module", missing)
    cases, notes = product_cases(1000.0)
    assert cases == [] and len(notes) == 1 and "skipped" in notes[0]


def test_bad_figure_name(tmp_path: pathlib.Path) -> None:
    with pytest.raises(ValueError):
        reproduce_3d("fig9", tmp_path)  # type: ignore[arg-type]
