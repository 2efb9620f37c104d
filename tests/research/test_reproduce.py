"""Tests for haptic_collab.research.reproduce (the paper's Fig. 7, 8 and 9 recomputed from the project code) and
for haptic_collab.research.plots, which draws them and writes ``haptic reproduce``'s files."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys
import textwrap
from typing import Any

import numpy as np
import pytest

from haptic_collab.research.reproduce import (
    FIGURES,
    Fig7Data,
    Fig8Data,
    Fig9Data,
    FigureData,
    figure_data,
    figure_names,
    json_text,
)
from haptic_collab.shared.stability import STABILITY_TOL

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _run_python(code: str, tmp_path: pathlib.Path) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a fresh interpreter (so global matplotlib state stays out of this one)."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
        check=False,
    )


@pytest.fixture(scope="module")
def data() -> dict[str, FigureData]:
    """Each figure's data, computed once by the pure package (no matplotlib needed)."""
    return {name: figure_data(name) for name in FIGURES}


@pytest.fixture(scope="module")
def out(tmp_path_factory: pytest.TempPathFactory) -> tuple[pathlib.Path, dict[str, dict[str, Any]]]:
    """Run reproduce_figures("all") once into a fresh (not yet existing) sub-directory."""
    pytest.importorskip("matplotlib")
    from haptic_collab.research.plots import reproduce_figures

    out_dir = tmp_path_factory.mktemp("figs") / "nested" / "out"
    return out_dir, reproduce_figures("all", out_dir)


def test_files_written(
    out: tuple[pathlib.Path, dict[str, dict[str, Any]]], data: dict[str, FigureData]
) -> None:
    out_dir, results = out
    assert set(results) == {"fig7", "fig8", "fig9"}
    for name in ("fig7", "fig8", "fig9"):
        png = out_dir / f"{name}.png"
        assert png.is_file()
        raw = png.read_bytes()
        assert raw[:8] == PNG_MAGIC
        assert len(raw) > 10_000
        text = (out_dir / f"{name}.json").read_text(encoding="utf-8")
        assert json.loads(text) == results[name]
        # the files hold what the pure computation gives, in its format
        assert text == json_text(data[name].result)
    # fig8's grid is written on one line, the others indented
    assert len((out_dir / "fig8.json").read_text(encoding="utf-8").splitlines()) == 1
    assert len((out_dir / "fig7.json").read_text(encoding="utf-8").splitlines()) > 20


def test_fig7_proportional_model(data: dict[str, FigureData]) -> None:
    d = data["fig7"]
    assert isinstance(d, Fig7Data)
    fig7 = d.result
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


def test_fig7_traces_are_the_plotted_runs(data: dict[str, FigureData]) -> None:
    d = data["fig7"]
    assert isinstance(d, Fig7Data)
    assert list(d.traces) == list(d.result["cases"]) == ["a", "b", "c"]
    n_ticks = round(d.result["run_s"] / d.result["servo_period_s"])
    for name, case in d.result["cases"].items():
        tr = d.traces[name]
        assert tr.t_s.shape == tr.probe_m.shape == tr.proxy_m.shape == (n_ticks,)
        assert tr.probe_m[-1] == d.result["probe"]["x_after_m"]
        assert float(np.max(np.abs(tr.proxy_m))) == case["max_abs_proxy_m"]
        if case["stable"]:
            assert tr.proxy_m[-1] == pytest.approx(case["final_proxy_m"], rel=1e-3)


def _verdict(fig8: dict[str, Any], kh: float, nti: float) -> bool:
    kh_axis, nti_axis = fig8["kh_over_ko"], fig8["nti_over_ko"]
    i = min(range(len(kh_axis)), key=lambda k: abs(kh_axis[k] - kh))
    j = min(range(len(nti_axis)), key=lambda k: abs(nti_axis[k] - nti))
    assert abs(kh_axis[i] - kh) < 0.02 and abs(nti_axis[j] - nti) < 0.02
    return bool(fig8["stable"][i][j])


def test_fig8_stability_region(data: dict[str, FigureData]) -> None:
    fig8 = data["fig8"].result
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


def test_fig8_grids_are_the_plotted_ones(data: dict[str, FigureData]) -> None:
    d = data["fig8"]
    assert isinstance(d, Fig8Data)
    shape = (len(d.result["kh_over_ko"]), len(d.result["nti_over_ko"]))
    assert d.kh_over_ko.tolist() == d.result["kh_over_ko"]
    assert d.nti_over_ko.tolist() == d.result["nti_over_ko"]
    assert d.spectral_radius.shape == d.stable.shape == shape
    assert d.stable.tolist() == d.result["stable"]
    assert float(d.spectral_radius.min()) == d.result["spectral_radius_min"]
    assert list(d.slices_spectral_radius) == [s["k_o"] for s in d.result["slices"].values()]
    for s in d.result["slices"].values():
        r = d.slices_spectral_radius[s["k_o"]]
        assert r.shape == shape
        assert float(np.mean(r < 1.0 - STABILITY_TOL)) == s["stable_fraction"]
    # the Fig. 9 gains, marked on the plane, are a stable point of it
    fig9_point = d.fig9_gains
    assert fig9_point == pytest.approx((100.0 / 300.0, 150.0 / 300.0))
    assert _verdict(d.result, *fig9_point) is True


def test_fig9_integral_term(data: dict[str, FigureData]) -> None:
    fig9 = data["fig9"].result
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


def test_fig9_traces_are_the_plotted_runs(data: dict[str, FigureData]) -> None:
    d = data["fig9"]
    assert isinstance(d, Fig9Data)
    assert set(d.traces) == {"pi", "p_only"}
    for key in ("pi", "p_only"):
        tr, case = d.traces[key], d.result[key]
        assert tr.probe_m[-1] * 1e3 == case["final_probe_mm"]
        assert tr.force_n[-1] == case["final_force_n"]
        offset_mm = (tr.probe_m[-1] - tr.proxy_m[-1]) * 1e3
        assert offset_mm == pytest.approx(case["steady_state_error_mm"], abs=0.2)


def test_figure_names_and_bad_names() -> None:
    assert figure_names("all") == ["fig7", "fig8", "fig9"]
    assert figure_names("fig8") == ["fig8"]
    with pytest.raises(ValueError, match="fig10"):
        figure_names("fig10")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="all"):
        figure_data("all")  # type: ignore[arg-type]


def test_single_figure_and_bad_name(tmp_path: pathlib.Path) -> None:
    pytest.importorskip("matplotlib")
    from haptic_collab.research.plots import reproduce_figures

    res = reproduce_figures("fig9", tmp_path)
    assert set(res) == {"fig9"}
    assert (tmp_path / "fig9.png").is_file()
    assert (tmp_path / "fig9.json").is_file()
    assert not (tmp_path / "fig7.json").exists()
    with pytest.raises(ValueError):
        reproduce_figures("fig10", tmp_path / "bad")  # type: ignore[arg-type]
    assert not (tmp_path / "bad").exists()


def test_computing_the_figures_does_not_import_matplotlib(tmp_path: pathlib.Path) -> None:
    proc = _run_python(
        """
        import sys
        from haptic_collab.research.reproduce import FIGURES, figure_data, json_text
        for name in FIGURES:
            json_text(figure_data(name).result)
        print(sorted(m for m in sys.modules if m.split(".")[0] == "matplotlib"))
        """,
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_plotting_leaves_the_backend_and_rc_settings_alone(tmp_path: pathlib.Path) -> None:
    pytest.importorskip("matplotlib")
    proc = _run_python(
        """
        import json, pathlib, sys
        import matplotlib
        matplotlib.use("svg")
        font_size = matplotlib.rcParams["font.size"]
        from haptic_collab.research.plots import reproduce_figures
        reproduce_figures("fig9", pathlib.Path("out"))
        print(json.dumps({
            "backend": matplotlib.get_backend(),
            "font_size_kept": matplotlib.rcParams["font.size"] == font_size,
            "pyplot": "matplotlib.pyplot" in sys.modules,
            "png": pathlib.Path("out/fig9.png").is_file(),
        }))
        """,
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == {
        "backend": "svg",
        "font_size_kept": True,
        "pyplot": False,
        "png": True,
    }


def test_cli_without_matplotlib_says_so_in_one_line(tmp_path: pathlib.Path) -> None:
    proc = _run_python(
        """
        import sys
        sys.modules["matplotlib"] = None  # as if the plots extra were not installed
        from haptic_collab.cli import main
        sys.exit(main(["reproduce", "fig7", "--out", "figs"]))
        """,
        tmp_path,
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr == (
        "haptic reproduce: error: the figures need matplotlib: pip install 'matplotlib>=3.8' "
        "(the plots extra; in a checkout: pip install -e '.[plots]')\n"
    )
    assert not (tmp_path / "figs").exists()
