"""Simulated devices, hand trajectories, profiles and the device factory."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from haptic_collab.client.devices.hid_backend import parse_hid_ids
from haptic_collab.client.devices.opener import list_devices, make_device
from haptic_collab.client.devices.profiles import SIM_PROFILES, get_sim_profile, sim_profile_names
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.devices.trajectories import (
    Press,
    Replay,
    ReplayError,
    Rest,
    hand_depth_for,
)
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.primitives import make_plane

T = 1e-3


def along(p: tuple[float, float, float], anchor: tuple[float, ...], n: tuple[float, ...]) -> float:
    """Signed distance [m] of p from the anchor along the outward normal."""
    return sum((a - b) * c for a, b, c in zip(p, anchor, n, strict=True))


# -- profiles ------------------------------------------------------------------------------------


def test_named_profiles_publish_vendor_like_limits() -> None:
    assert sim_profile_names() == ["phantom-desktop", "touch"]
    pd, touch = get_sim_profile("phantom-desktop"), get_sim_profile("touch")
    assert pd.limits.max_force_n == 7.9 and touch.limits.max_force_n == 3.3
    assert pd.limits.max_stiffness_n_per_m == pytest.approx(1000.0)
    assert touch.limits.max_stiffness_n_per_m == pytest.approx(400.0)
    for p in SIM_PROFILES.values():
        assert p.limits.has_force_output and p.encoder_resolution_m > 0
    with pytest.raises(ValueError, match="phantom-desktop"):
        get_sim_profile("falcon")


def _wall_ring_mm(profile: str, stiffness_ratio: float) -> float:
    """Peak to peak [mm] of a light hand resting 5 mm into a wall at ratio * the max stiffness."""
    prof = get_sim_profile(profile)
    k = stiffness_ratio * prof.limits.max_stiffness_n_per_m
    light = HandParams(stiffness_n_per_m=100.0, damping_n_s_per_m=1.0, mass_kg=0.05)
    target = (0.0, 0.0, -0.005)
    limits = replace(prof.limits.centered_at(target), max_stiffness_n_per_m=k)
    dev = SimDevice(prof, lambda t: target, light, limits=limits)
    dev.open()
    core = ServoCore(dev, ServoConfig(), local_model=LocalModelParams(k_h=1.0))
    core.set_patch(make_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), k, 0.0)
    core.enable_forces()
    z = []
    for n in range(3000):
        t = n * T
        if n % 10 == 0:
            core.notify_link(t)
        core.tick(t)
        snap = core.latest()
        assert snap is not None
        z.append(snap.probe_m[2])
    return float(np.ptp(z[-1000:]) * 1000.0)


@pytest.mark.parametrize("profile", ["phantom-desktop", "touch"])
def test_the_max_stiffness_is_a_wall_a_light_hand_can_rest_on(profile: str) -> None:
    """The profile's K_max is stable with the lightest hand, and not far below where it rings."""
    res_mm = get_sim_profile(profile).encoder_resolution_m * 1000.0
    assert _wall_ring_mm(profile, 1.0) <= 2 * res_mm + 1e-9  # still, to an encoder count or two
    assert _wall_ring_mm(profile, 8.0) > 0.3  # eight times stiffer: the wall rings


# -- trajectories --------------------------------------------------------------------------------

ANCHOR = (0.01, -0.02, 0.08)
NORMAL = (0.0, 0.6, 0.8)


def test_press_approaches_pushes_holds_and_withdraws_along_the_normal() -> None:
    p = Press(ANCHOR, NORMAL, delay_s=0.5)
    d = [along(p(t), ANCHOR, NORMAL) for t in (0.0, 0.5, 1.5, 2.5, 3.5, 4.5, 5.5, 9.0)]
    assert d[0] == pytest.approx(0.03) and d[1] == pytest.approx(0.03)  # waiting outside
    assert d[2] == pytest.approx(0.0, abs=1e-12)  # at the surface after the approach
    assert d[3] == pytest.approx(-0.02) and d[4] == pytest.approx(-0.02)  # pressed and held
    assert d[6] == pytest.approx(0.03) and d[7] == pytest.approx(0.03)  # withdrawn, stays
    assert p.duration_s == pytest.approx(5.5)
    # the hand target stays on the normal line through the anchor
    x = p(2.0)
    off = [
        xi - ai - along(x, ANCHOR, NORMAL) * ni
        for xi, ai, ni in zip(x, ANCHOR, NORMAL, strict=True)
    ]
    assert max(abs(o) for o in off) < 1e-12


def test_scripted_hands_move_smoothly() -> None:
    for traj in (Press(ANCHOR, NORMAL), Rest(ANCHOR, NORMAL, delay_s=0.2)):
        pts = [traj(k * T) for k in range(6000)]
        speeds = [math.dist(a, b) / T for a, b in zip(pts, pts[1:], strict=False)]
        accels = [abs(b - a) / T for a, b in zip(speeds, speeds[1:], strict=False)]
        assert max(speeds) < 0.1  # m/s: a calm hand, far below the devices' velocity limits
        assert max(accels) < 1.0  # m/s^2: no jerks at the way-points


def test_rest_holds_a_couple_of_mm_inside() -> None:
    r = Rest(ANCHOR, NORMAL)
    assert along(r(0.0), ANCHOR, NORMAL) == pytest.approx(0.03)
    assert along(r(1.0), ANCHOR, NORMAL) == pytest.approx(-0.002)
    assert along(r(100.0), ANCHOR, NORMAL) == pytest.approx(-0.002)


@pytest.mark.parametrize(
    "kwargs", [{"normal": (0, 0, 0)}, {"depth_m": -0.01}, {"hold_s": math.nan}, {"anchor": (0, 1)}]
)
def test_bad_trajectory_parameters_are_refused(kwargs: dict[str, object]) -> None:
    args: dict[str, object] = {"anchor": ANCHOR, "normal": NORMAL, **kwargs}
    with pytest.raises(ValueError):
        Press(**args)  # type: ignore[arg-type]


def test_hand_depth_for_inverts_the_series_springs() -> None:
    assert hand_depth_for(0.01, 300.0, 300.0) == pytest.approx(0.02)
    assert hand_depth_for(0.01, 600.0, 300.0) == pytest.approx(0.03)
    with pytest.raises(ValueError):
        hand_depth_for(0.01, 0.0)


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "hand.csv"
    p.write_text(text)
    return p


def test_replay_interpolates_a_recorded_csv(tmp_path: Path) -> None:
    path = write(
        tmp_path, "t_s,x_m,y_m,z_m,note\n0.0,0,0,0.1,a\n1.0,0.01,0,0.08,b\n2.0,0.01,0,0.06,c\n"
    )
    r = Replay.from_csv(path)
    assert r(0.5) == pytest.approx((0.005, 0.0, 0.09))
    assert r(-1.0) == pytest.approx((0.0, 0.0, 0.1))  # before the first sample: hold it
    assert r(5.0) == pytest.approx((0.01, 0.0, 0.06))  # after the last: hold it
    assert r.duration_s == 2.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty file"),
        ("t,x,y,z\n0,0,0,0\n", "lacks column"),
        ("t_s,x_m,y_m,z_m\n", "no data rows"),
        ("t_s,x_m,y_m,z_m\n0,0,0,0\n0.1,0,zero,0\n", "row 3"),
        ("t_s,x_m,y_m,z_m\n0,0,0,0\n0.1,0,0\n", "row 3"),
        ("t_s,x_m,y_m,z_m\n0,0,0,0\n0,0,0,1\n", "not after"),
        ("t_s,x_m,y_m,z_m\n0,0,0,nan\n", "non-finite"),
    ],
)
def test_malformed_replay_files_say_what_is_wrong(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(ReplayError, match=message):
        Replay.from_csv(write(tmp_path, text))


def test_missing_replay_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ReplayError, match="cannot open"):
        make_device(f"sim:replay:{tmp_path / 'nope.csv'}", ANCHOR, NORMAL)


# -- the factory ---------------------------------------------------------------------------------


def test_make_device_parses_specs(tmp_path: Path) -> None:
    d = make_device("sim:press", ANCHOR, NORMAL)
    assert isinstance(d, SimDevice) and isinstance(d.trajectory, Press)
    assert d.limits.max_force_n == 7.9
    lo, hi = d.limits.workspace_min_m, d.limits.workspace_max_m
    assert all(a < c < b for a, b, c in zip(lo, hi, ANCHOR, strict=True))  # workspace around it
    d = make_device("sim:rest", ANCHOR, NORMAL, profile="touch", trajectory_options={"delay_s": 2})
    assert isinstance(d, SimDevice) and isinstance(d.trajectory, Rest)
    assert d.trajectory.delay_s == 2 and d.limits.max_force_n == 3.3
    path = write(tmp_path, "t_s,x_m,y_m,z_m\n0,0,0,0.1\n1,0,0,0.05\n")
    d = make_device(f"sim:replay:{path}", ANCHOR, NORMAL)
    assert isinstance(d, SimDevice) and isinstance(d.trajectory, Replay)
    d = make_device("hid:256f:c635", ANCHOR, NORMAL)  # a SpaceMouse Compact; not opened
    assert d.name == "spacemouse:256f:c635" and not d.limits.has_force_output
    d = make_device("hid:1209:0001", ANCHOR, NORMAL)  # bundled example profile
    assert d.name == "hid:example-3dof-force" and d.limits.has_force_output


@pytest.mark.parametrize(
    ("spec", "kwargs", "message"),
    [
        ("sim:wave", {}, "unknown simulated device"),
        ("sim", {}, "unknown simulated device"),
        ("usb:1:2", {}, "unknown device spec"),
        ("hid:zz:0001", {}, "VID:PID"),
        ("hid:1234", {}, "VID:PID"),
        ("hid:dead:beef", {}, "no HID profile"),
        ("sim:press", {"profile": "falcon"}, "unknown device profile"),
        ("sim:press", {"trajectory_options": {"depth": 0.01}}, "bad trajectory option"),
        ("sim:press", {"normal": (0, 0, 0)}, "non-zero"),
    ],
)
def test_make_device_refuses_bad_specs(spec: str, kwargs: dict[str, object], message: str) -> None:
    args: dict[str, object] = {"anchor": ANCHOR, "normal": NORMAL, **kwargs}
    with pytest.raises(ValueError, match=message):
        make_device(spec, **args)  # type: ignore[arg-type]


def test_parse_hid_ids_accepts_0x() -> None:
    assert parse_hid_ids("0x046d:0xc626") == (0x046D, 0xC626)


def test_list_devices_includes_the_simulated_profiles() -> None:
    devs = list_devices()
    sims = {d["profile"] for d in devs if d["kind"] == "sim"}
    assert sims == {"phantom-desktop", "touch"}
    # every device entry names its backend; every backend entry says whether it is usable
    devices = [d for d in devs if d["kind"] != "backend"]
    assert all(d["spec"].startswith(f"{d['backend']}:") for d in devices)
    names = {d["name"] for d in devs if d["kind"] == "backend"}
    assert {"sim", "hid", "openhaptics", "forcedimension", "haply"} <= names


# -- the simulated device's physics ---------------------------------------------------------------


def sim(traj, profile: str = "phantom-desktop", hand: HandParams | None = None) -> SimDevice:  # type: ignore[no-untyped-def]
    p = get_sim_profile(profile)
    d = SimDevice(p, traj, hand, limits=p.limits.centered_at((0.0, 0.0, 0.0)))
    d.open()
    return d


def test_free_hand_brings_the_handle_to_its_target() -> None:
    d = sim(lambda t: (0.01, 0.0, 0.0) if t > 0 else (0.0, 0.0, 0.0))
    d.read(0.0)
    for k in range(1, 2001):
        x = d.read(k * T)
    assert x[0] == pytest.approx(0.01, abs=d.profile.encoder_resolution_m)
    assert abs(d.velocity_m_s[0]) < 1e-3


def test_a_constant_force_deflects_the_hand_by_f_over_k() -> None:
    hand = HandParams(stiffness_n_per_m=200.0)
    d = sim(lambda t: (0.0, 0.0, 0.0), hand=hand)
    d.enable_forces()
    d.read(0.0)
    d.write(0.0, 0.0, 1.0)  # 1 N up on the user's hand
    for k in range(1, 3001):
        x = d.read(k * T)
    assert x[2] == pytest.approx(1.0 / 200.0, abs=2 * d.profile.encoder_resolution_m)


def test_forces_saturate_at_the_device_peak_and_are_ignored_when_disabled() -> None:
    d = sim(lambda t: (0.0, 0.0, 0.0), profile="touch")
    d.write(0.0, 0.0, 2.0)
    assert d.applied_force_n == (0.0, 0.0, 0.0)  # forces not enabled
    d.enable_forces()
    d.write(30.0, 0.0, 40.0)
    assert math.hypot(*d.applied_force_n) == pytest.approx(3.3)
    assert d.applied_force_n[0] / d.applied_force_n[2] == pytest.approx(0.75)  # direction kept
    d.disable_forces()
    assert d.applied_force_n == (0.0, 0.0, 0.0)


def test_positions_are_quantized_to_the_encoder() -> None:
    d = sim(lambda t: (0.0123456, -0.00111, 0.0))
    x = d.read(0.0)
    res = d.profile.encoder_resolution_m
    for xi in x:
        assert xi / res == pytest.approx(round(xi / res), abs=1e-6)
    assert x[0] == pytest.approx(0.0123456, abs=res / 2 + 1e-12)


def test_the_handle_stops_at_the_workspace_edge() -> None:
    d = sim(lambda t: (1.0, 0.0, 0.0) if t > 0 else (0.0, 0.0, 0.0))
    d.read(0.0)
    for k in range(1, 3001):
        x = d.read(k * T)
    assert x[0] == pytest.approx(d.limits.workspace_max_m[0], abs=d.profile.encoder_resolution_m)


def test_press_settles_the_probe_at_the_predicted_depth_against_a_rendered_wall() -> None:
    """Closed loop: sim device + P local model on a rigid plane, the hand pressing in."""
    anchor, normal = (0.0, 0.0, 0.05), (0.0, 0.0, 1.0)
    k_h = 300.0
    depth = hand_depth_for(0.01, k_h)  # hand 300 N/m against 300 N/m: 20 mm for 10 mm
    dev = make_device("sim:press", anchor, normal, trajectory_options={"depth_m": depth})
    dev.open()
    core = ServoCore(dev, ServoConfig(link_timeout_s=math.inf))
    core.enable_forces()
    core.set_patch(make_plane(anchor, normal), k_h, 0.0)
    pens = []
    for k in range(6000):
        core.tick(k * T)
        snap = core.latest()
        assert snap is not None
        pens.append(snap.penetration_m)
    hold = pens[3500:4000]  # inside the hold phase (2-4 s), after settling
    assert sum(hold) / len(hold) == pytest.approx(0.010, abs=2e-4)
    assert max(hold) - min(hold) < 2e-4  # steady: the coupled loop does not oscillate
    assert core.latest().force_n[2] == 0.0  # type: ignore[union-attr]  # withdrawn at the end
    assert pens[-1] == pytest.approx(-0.03, abs=1e-3)


def test_the_hand_clock_starts_at_the_first_read() -> None:
    d = make_device("sim:press", ANCHOR, NORMAL)
    d.open()
    t0 = 12345.678  # a monotonic clock is far from zero
    x = d.read(t0)
    assert along(x, ANCHOR, NORMAL) == pytest.approx(0.03, abs=1e-4)  # start of the press
    for k in range(1, 2501):
        x = d.read(t0 + k * T)
    assert along(x, ANCHOR, NORMAL) < -0.005  # 2.5 s later: pressed in (no object here)


def test_continuous_force_is_stated_and_bounded_by_the_peak() -> None:
    desktop, touch = get_sim_profile("phantom-desktop").limits, get_sim_profile("touch").limits
    assert (desktop.max_force_n, desktop.max_continuous_force_n) == (7.9, 1.75)
    assert (touch.max_force_n, touch.max_continuous_force_n) == (3.3, 0.88)
    with pytest.raises(ValueError, match="max_continuous_force_n"):
        replace(desktop, max_continuous_force_n=8.0)
