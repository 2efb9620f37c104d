"""Tests for shared.reproduce: the paper's Fig. 7, 8 and 9 recomputed from the project code."""

from __future__ import annotations

import json
import pathlib
from typing import Any

import pytest

from haptic_collab.shared.reproduce import reproduce

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def out(tmp_path_factory: pytest.TempPathFactory) -> tuple[pathlib.Path, dict[str, dict[str, Any]]]:
    """Run reproduce("all") once into a fresh (not yet existing) sub-directory."""
    out_dir = tmp_path_factory.mktemp("figs") / "nested" / "out"
    return out_dir, reproduce("all", out_dir)


def test_files_written(out: tuple[pathlib.Path, dict[str, dict[str, Any]]]) -> None:
    out_dir, results = out
    assert set(results) == {"fig7", "fig8", "fig9"}
    for name in ("fig7", "fig8", "fig9"):
        png = out_dir / f"{name}.png"
        assert png.is_file()
        data = png.read_bytes()
        assert data[:8] == PNG_MAGIC
        assert len(data) > 10_000
        js = out_dir / f"{name}.json"
        assert json.loads(js.read_text(encoding="utf-8")) == results[name]


def test_fig7_proportional_model(out: tuple[pathlib.Path, dict[str, dict[str, Any]]]) -> None:
    fig7 = out[1]["fig7"]
    assert "bilateral" in fig7["model"]
    a, b, c = (fig7["cases"][k] for k in "abc")
    assert (a["k_o"], a["k_h"]) == (900.0, 100.0)
    # (a) K_o = 9 K_h: settles at once, x_o / x_h = K_h / (K_h + K_o) = 0.1 (eq. 11)
    assert a["stable"] is True
    assert a["steady_state_ratio"] == pytest.approx(0.1, abs=0.01)
    assert a["settling_time_s"] < 0.5
    assert a["spectral_radius"] == pytest.approx(100.0 / 900.0)
    # (b) K_h close to K_o: stable but oscillates for seconds
    assert b["stable"] is True
    assert b["settling_time_s"] > 1.5
    assert b["steady_state_ratio"] == pytest.approx(190.0 / 390.0, abs=0.01)
    assert b["spectral_radius"] == pytest.approx(0.95)
    # (c) K_h > K_o: diverges (eq. 8 violated)
    assert c["stable"] is False
    assert c["settling_time_s"] is None
    assert c["steady_state_ratio"] is None
    assert c["overshoot"] is None
    assert c["spectral_radius"] > 1.0
    assert c["max_abs_proxy_m"] > 1.0


def _verdict(fig8: dict[str, Any], kh: float, nti: float) -> bool:
    kh_axis, nti_axis = fig8["kh_over_ko"], fig8["nti_over_ko"]
    i = min(range(len(kh_axis)), key=lambda k: abs(kh_axis[k] - kh))
    j = min(range(len(nti_axis)), key=lambda k: abs(nti_axis[k] - nti))
    assert abs(kh_axis[i] - kh) < 0.02 and abs(nti_axis[j] - nti) < 0.02
    return bool(fig8["stable"][i][j])


def test_fig8_stability_region(out: tuple[pathlib.Path, dict[str, dict[str, Any]]]) -> None:
    fig8 = out[1]["fig8"]
    assert fig8["n"] == 50
    assert fig8["servo_period_s"] == pytest.approx(0.001)
    assert len(fig8["stable"]) == len(fig8["kh_over_ko"]) >= 100
    assert all(len(row) == len(fig8["nti_over_ko"]) for row in fig8["stable"])
    assert min(fig8["nti_over_ko"]) > 0.0
    assert fig8["agreement_fraction"] >= 0.99
    assert fig8["agrees_with_eq15"] is True
    assert fig8["spectral_radius_min"] < 0.05
    assert _verdict(fig8, 0.5, 0.5) is True
    assert _verdict(fig8, 1.5, 0.2) is False
    assert _verdict(fig8, 0.5, 2.0) is False
    assert _verdict(fig8, 2.0, 2.5) is True  # inside the wedge up to (3 K_o, 4 K_o)


def test_fig9_integral_term(out: tuple[pathlib.Path, dict[str, dict[str, Any]]]) -> None:
    fig9 = out[1]["fig9"]
    assert (fig9["k_o"], fig9["k_h"], fig9["theta_m"]) == (300.0, 100.0, 0.004)
    assert fig9["i_gain"] == pytest.approx(3000.0)
    assert fig9["nti"] == pytest.approx(150.0)
    assert "3000" in fig9["i_gain_reason"]
    pi, p_only = fig9["pi"], fig9["p_only"]
    # PI: the steady-state error is the 4 mm threshold of eq. 17
    assert pi["steady_state_error_mm"] == pytest.approx(4.0, abs=0.2)
    # P alone: eq. 11 error K_o / (K_h + K_o) * x_h = 22.5 mm
    assert p_only["steady_state_error_mm"] > 3.0 * pi["steady_state_error_mm"]
    assert p_only["steady_state_error_mm"] == pytest.approx(22.5, abs=0.2)
    assert pi["settling_time_s"] < 1.0
    assert pi["spectral_radius"] < 1.0
    # the contact is never lost after the step (unilateral model keeps pushing)
    assert pi["min_penetration_after_step_mm"] > 0.0
    # the literal reading of the printed gain would be far too slow
    assert fig9["literal_reading"]["time_constant_s"] > 60.0


def test_single_figure_and_bad_name(tmp_path: pathlib.Path) -> None:
    res = reproduce("fig9", tmp_path)
    assert set(res) == {"fig9"}
    assert (tmp_path / "fig9.png").is_file()
    assert not (tmp_path / "fig7.json").exists()
    with pytest.raises(ValueError):
        reproduce("fig10", tmp_path)  # type: ignore[arg-type]
