"""``haptic gains`` and the full-loop flags of ``haptic stability`` as a user meets them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from haptic_collab.cli import main
from haptic_collab.shared.full_loop import DEFAULT_HAND, DEFAULT_HAND_BOX

ROOT = Path(__file__).resolve().parents[2]

GAINS_KEYS = {
    "k_h",
    "i_gain",
    "b_h",
    "proxy_hold",
    "worst_spectral_radius",
    "hand_box",
    "felt_stiffness_ratio_1hz",
    "felt_stiffness_ratio_8hz",
    "design_ms",
}
HAND_FLAGS = {
    "--hand-mass": str(DEFAULT_HAND.mass_kg),
    "--hand-damping": str(DEFAULT_HAND.damping_n_s_per_m),
    "--hand-stiffness": str(DEFAULT_HAND.stiffness_n_per_m),
}


def _exit_code(argv: list[str]) -> int:
    """``main``'s status, whether it returns it or argparse exits with it."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else 1


def _json(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict[str, object]:
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    out = json.loads(captured.out)
    assert isinstance(out, dict)
    return out


def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert _exit_code(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert "Traceback" not in captured.err
    return lines[0]


# ------------------------------------------------------------------------------------- gains
def test_gains_json_has_the_documented_keys_and_stable_bounded_gains(capsys) -> None:
    out = _json(capsys, ["gains", "--k-o", "1000", "--local-model", "p", "--json"])
    assert GAINS_KEYS <= out.keys()
    assert out["proxy_hold"] in ("zoh", "foh")
    assert out["i_gain"] == 0.0  # a P local model
    assert 0.0 < out["worst_spectral_radius"] < 1.0  # type: ignore[operator]
    assert 0.0 < out["k_h"] <= 1000.0  # type: ignore[operator]  # phantom-desktop K_max
    assert 0.0 <= out["b_h"] <= 10.0  # type: ignore[operator]  # phantom-desktop B_max
    assert 0.0 < out["felt_stiffness_ratio_1hz"]  # type: ignore[operator]
    assert out["design_ms"] >= 0.0  # type: ignore[operator]
    box = out["hand_box"]
    assert isinstance(box, dict)
    assert box == {
        "mass_kg": list(DEFAULT_HAND_BOX.mass_kg),
        "stiffness_n_per_m": list(DEFAULT_HAND_BOX.stiffness_n_per_m),
        "damping_n_s_per_m": list(DEFAULT_HAND_BOX.damping_n_s_per_m),
    }
    for lo, hi in box.values():
        assert lo <= hi


def test_gains_from_haptic_gains_are_stable_per_haptic_stability_for_the_simulated_hand(
    capsys,
) -> None:
    g = _json(capsys, ["gains", "--k-o", "1000", "--local-model", "p", "--json"])
    args = ["stability", "--k-o", "1000", "--k-h", repr(g["k_h"]), "--b-h", repr(g["b_h"])]
    args += ["--proxy-hold", str(g["proxy_hold"]), "--own-gain", repr(g["own_gain"]), "--json"]
    for flag, value in HAND_FLAGS.items():
        args += [flag, value]
    out = _json(capsys, args)
    full = out["full_loop"]
    assert isinstance(full, dict)
    assert full["stable"] is True and full["spectral_radius"] < 1.0


def test_gains_profile_touch_stays_within_the_touch_limits(capsys) -> None:
    base = ["gains", "--k-o", "5000", "--local-model", "p", "--json"]
    touch = _json(capsys, [*base, "--profile", "touch"])
    assert touch["k_h"] <= 400.0  # type: ignore[operator]
    assert touch["b_h"] <= 5.0  # type: ignore[operator]
    assert touch["worst_spectral_radius"] < 1.0  # type: ignore[operator]
    # on this stiff object the phantom-desktop renders stiffer: the profile is what bounds it
    phantom = _json(capsys, base)
    assert phantom["k_h"] > 400.0  # type: ignore[operator]


def test_gains_text_output_names_the_gains(capsys) -> None:
    assert main(["gains", "--k-o", "1000", "--local-model", "p"]) == 0
    out = capsys.readouterr().out
    assert "K_h =" in out and "B_h =" in out and "spectral radius" in out


@pytest.mark.parametrize(
    "argv",
    [
        ["gains", "--k-o", "-1"],
        ["gains", "--k-o", "0"],
        ["gains", "--k-o", "1000", "--margin", "1.5"],
        ["gains", "--k-o", "1000", "--margin", "1.0"],
        ["gains", "--k-o", "1000", "--profile", "no-such-device"],
        ["gains", "--k-o", "1000", "--local-model", "pd"],
        ["gains", "--k-o", "1000", "--sim-rate", "30"],  # 1000 / 30 is not whole
        ["gains", "--k-o", "1000", "--delay-ticks", "-2"],
    ],
    ids=lambda a: " ".join(a[2:]),
)
def test_gains_bad_values_exit_2_with_one_line(capsys, argv: list[str]) -> None:
    line = _one_line_error(capsys, argv)
    assert "error" in line


def test_unknown_profile_error_lists_the_known_ones(capsys) -> None:
    line = _one_line_error(capsys, ["gains", "--k-o", "1000", "--profile", "no-such-device"])
    assert "no-such-device" in line and "phantom-desktop" in line and "touch" in line


def test_gains_runs_as_a_module() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "haptic_collab.cli", "gains", "--k-o", "300", "--local-model", "p"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    assert "K_h =" in proc.stdout


# --------------------------------------------------------------------- stability with the hand
def test_stability_paper_loop_stable_but_full_loop_unstable_with_the_hand(capsys) -> None:
    args = ["stability", "--k-o", "1000", "--k-h", "700", "--json"]
    for flag, value in HAND_FLAGS.items():
        args += [flag, value]
    out = _json(capsys, args)
    assert out["stable"] is True  # eq. 8: K_h < K_o
    full = out["full_loop"]
    assert isinstance(full, dict)
    assert full["stable"] is False
    assert full["spectral_radius"] > 1.0
    assert 0 <= full["worst_sample_tick"] < 50


def test_stability_text_reports_the_full_loop_verdict(capsys) -> None:
    args = ["stability", "--k-o", "1000", "--k-h", "700"]
    for flag, value in HAND_FLAGS.items():
        args += [flag, value]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert out.startswith("STABLE")
    assert "full loop" in out and "UNSTABLE" in out


def test_stability_without_hand_flags_has_null_full_loop(capsys) -> None:
    out = _json(capsys, ["stability", "--k-o", "1000", "--k-h", "700", "--json"])
    assert out["stable"] is True
    assert "full_loop" in out and out["full_loop"] is None


@pytest.mark.parametrize(
    "flags",
    [["--hand-mass"], ["--hand-damping"], ["--hand-stiffness"]]
    + [["--hand-mass", "--hand-damping"], ["--hand-mass", "--hand-stiffness"]]
    + [["--hand-damping", "--hand-stiffness"]],
    ids=lambda f: "+".join(x.removeprefix("--hand-") for x in f),
)
def test_stability_with_some_hand_flags_exits_2_with_one_line(capsys, flags: list[str]) -> None:
    args = ["stability", "--k-o", "1000", "--k-h", "700", "--json"]
    for flag in flags:
        args += [flag, HAND_FLAGS[flag]]
    line = _one_line_error(capsys, args)
    assert "--hand-mass" in line and "--hand-damping" in line and "--hand-stiffness" in line


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--hand-mass", "0"), ("--hand-damping", "-1"), ("--hand-stiffness", "nan"), ("--b-h", "-1")],
)
def test_stability_bad_hand_values_exit_2(capsys, flag: str, value: str) -> None:
    args = ["stability", "--k-o", "1000", "--k-h", "700"]
    for f, v in HAND_FLAGS.items():
        args += [f, value if f == flag else v]
    if flag == "--b-h":
        args += [flag, value]
    _one_line_error(capsys, args)


def test_stability_probe_damper_and_foh_change_the_full_loop_verdict(capsys) -> None:
    """K_h = 700 N/m on 1000 N/m vibrates with the simulated hand; the damper and foh tame it."""
    base = ["stability", "--k-o", "1000", "--k-h", "700", "--json"]
    for flag, value in HAND_FLAGS.items():
        base += [flag, value]
    bare = _json(capsys, base)["full_loop"]
    damped = _json(capsys, [*base, "--b-h", "10", "--proxy-hold", "foh"])["full_loop"]
    assert isinstance(bare, dict) and isinstance(damped, dict)
    assert bare["stable"] is False
    assert damped["stable"] is True and damped["spectral_radius"] < 1.0


def test_a_damped_object_is_shown_beside_what_its_design_is_felt_as(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # with B_o the design is judged against eq. 9's object, stiffer to a quick press: the text
    # says how stiff that object is, so 1.7 K_o at 8 Hz does not read as a fault
    assert main(["gains", "--k-o", "300", "--local-model", "p", "--b-o", "200"]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if "felt stiffness / K_o" in x)
    own = line.split("eq. 9: ")[1].rstrip(")").split(" and ")
    # |K_o + B_o (1 - e^{-j w / 20 Hz})| / K_o at 1 and 8 Hz
    assert float(own[0]) == pytest.approx(1.053, abs=1e-3)
    assert float(own[1]) == pytest.approx(2.241, abs=1e-3)
    assert main(["gains", "--k-o", "300", "--local-model", "p"]) == 0
    assert "eq. 9" not in capsys.readouterr().out


def test_a_design_for_a_damped_object_holds_up_to_its_one_tick_stiffness(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # as a client's gain-table cell (shared.gains.table.cell_k_o_range): checked up to 1.25 K_o,
    # or up to K_o + B_o where that is higher (docs/gains.md); down to 0.85 K_o, or to K_o / 1.25
    # where that costs less than a JND, as it does here (shared.gains.design.softest_k_o)
    base = ["gains", "--k-o", "300", "--local-model", "p", "--sim-rate", "100", "--json"]
    damped = _json(capsys, [*base, "--b-o", "472"])["k_o_range"]
    assert damped[1] == pytest.approx(772.0)
    assert damped[0] == pytest.approx(240.0)
    assert _json(capsys, [*base, "--b-o", "50"])["k_o_range"][1] == pytest.approx(375.0)
