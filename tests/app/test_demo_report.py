"""The demo report's coupling: B's force rise [N] and surface displacement [mm], measured while B
rests settled, never while B is still approaching or its force is still building up."""

from __future__ import annotations

import numpy as np
import pytest

from haptic_collab.demo_report import (
    B_SETTLE_S,
    RELEASE_SETTLE_S,
    STABLE_P2P_MM,
    coupling_report,
    hold_shake_mm,
    landing_settled_s,
    largest_p2p,
    timeline,
)
from haptic_collab.shared.gains.policy import MIN_DECAY_RATE_PER_S

RATE = 1000.0
REST_N, HOLD_N = 0.20, 0.24  # B's force at rest and while A holds
BULGE_M = 0.0013  # how far the side moves out while A holds
SIDE = np.array([0.1, 0.0, 0.0])  # B rests on +x: outward is +x


def telemetry(
    duration_s: float, onset_s: float, hold_n: float = HOLD_N, bulge_m: float = BULGE_M
) -> tuple[dict[str, np.ndarray], tuple]:
    """B's telemetry: force on at ``onset_s``, building up over 1 s, bulged out during A's press."""
    tl = timeline(duration_s)
    t = np.arange(0.0, duration_s, 1.0 / RATE)
    # A's press bulges B's side out: ramps in over A's press, back out over the release
    press = np.clip((t - tl.contact_s) / tl.press_s, 0.0, 1.0)
    release = np.clip((t - tl.hold_end_s) / tl.release_s, 0.0, 1.0)
    bulge = press * (1.0 - release)
    on = t >= onset_s
    build_up = np.clip((t - onset_s) / 0.9, 0.0, 1.0)  # the PI integral reaching B's rest force
    force = np.where(on, (REST_N * build_up + (hold_n - REST_N) * bulge), 0.0)
    proxy = SIDE[None, :] + np.outer(bulge_m * bulge, [1.0, 0.0, 0.0])
    cols = {
        "t_s": t,
        "force_n": force,
        "force_x_n": force,
        "force_y_n": np.zeros_like(t),
        "force_z_n": np.zeros_like(t),
        "proxy_x_m": proxy[:, 0],
        "proxy_y_m": proxy[:, 1],
        "proxy_z_m": proxy[:, 2],
        "in_contact": on.astype(float),
    }
    hold = (tl.hold_end_s - 1.0, tl.hold_end_s)
    return cols, (tl, hold)


@pytest.mark.parametrize("duration_s", [12.0, 16.0, 20.0])
def test_the_coupling_is_a_force_rise_and_a_displacement(duration_s: float) -> None:
    # B's force comes on at 2.2 s: in a 12 s run the old "before" window (2.5-3.75 s) caught it
    # still building up (ratio 2.9 instead of 1.2)
    b, (tl, hold) = telemetry(duration_s, onset_s=2.2)
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["b_force_rise_n"] == pytest.approx(HOLD_N - REST_N, abs=2e-3)
    assert c["b_surface_displacement_mm"] == pytest.approx(BULGE_M * 1000.0, abs=0.02)
    assert c["b_force_at_rest_n"] == pytest.approx(REST_N, abs=2e-3)
    assert c["ratio"] == pytest.approx(HOLD_N / REST_N, abs=0.02)
    assert c["baseline"] == "before A's press"
    rest = c["rest_window_s"]
    assert 2.2 + B_SETTLE_S <= rest[0] < 2.2 + B_SETTLE_S + 0.1 and rest[1] <= tl.contact_s


@pytest.mark.parametrize(
    "hold_n, bulge_m, feels",
    [
        (0.24, 0.0013, True),  # the side bulges out and pushes B's hand back: +20 %
        (0.16, -0.0013, True),  # the side is drawn in (a membrane near A's dent): -20 %
        (0.24, -0.0013, False),  # a force that does not follow the surface is not A's press
        (0.205, 0.0013, False),  # +2.5 %: below the force JND
        (0.24, 0.00005, False),  # the surface barely moved
    ],
)
def test_b_feels_a_when_its_force_follows_the_moving_surface_by_a_jnd(hold_n, bulge_m, feels):
    b, (tl, hold) = telemetry(12.0, onset_s=2.2, hold_n=hold_n, bulge_m=bulge_m)
    assert coupling_report(b, tl, hold, b_approach_end_s=1.0)["b_feels_a"] is feels


def test_a_surface_drawn_away_from_b_is_felt_when_b_loses_contact() -> None:
    """A side drawn in by more than B's own dent (the hex nut's flat, the bowl's rim) leaves B's
    finger while A holds: B's force falls to nothing, which B feels, and the report says so."""
    b, (tl, hold) = telemetry(12.0, onset_s=2.2, hold_n=0.0, bulge_m=-0.0013)
    lost = (b["t_s"] >= hold[0] - 0.5) & (b["t_s"] <= hold[1] + 0.1)
    b["in_contact"] = np.where(lost, 0.0, b["in_contact"])
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["b_force_rise_n"] == pytest.approx(-REST_N, abs=2e-3)
    assert c["b_surface_displacement_mm"] == pytest.approx(-1.3, abs=0.02)
    assert c["b_feels_a"] is True


def test_a_late_contact_is_measured_after_the_release() -> None:
    # B's contact comes on just before A touches (a slow network): no settled rest before the press
    b, (tl, hold) = telemetry(16.0, onset_s=tl_contact(16.0) - 0.5)
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["baseline"] == "after A's release"
    assert c["rest_window_s"][0] >= tl.hold_end_s + tl.release_s + RELEASE_SETTLE_S
    assert c["b_force_rise_n"] == pytest.approx(HOLD_N - REST_N, abs=2e-3)
    assert c["b_surface_displacement_mm"] == pytest.approx(BULGE_M * 1000.0, abs=0.02)


def test_no_settled_rest_anywhere_is_not_a_number() -> None:
    b, (tl, hold) = telemetry(12.0, onset_s=100.0)  # B never touched
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["b_force_rise_n"] is None and c["b_surface_displacement_mm"] is None
    assert c["ratio"] is None and c["rest_window_s"] is None


def tl_contact(duration_s: float) -> float:
    return timeline(duration_s).contact_s


def test_a_hold_is_judged_for_shake_not_for_creep_nor_for_a_change_of_gains() -> None:
    """hold_shake_mm (the loopback test's judgement of a hold; the demo judges the whole hold
    in test_demo_verdict.py): a shaking hold fails, a creeping one and a moved equilibrium pass."""
    t = np.arange(0.0, 3.0, 1.0 / RATE)
    window = (2.0, 3.0)
    k_h = np.full_like(t, 43.0)
    still = np.full_like(t, 0.0066)
    assert hold_shake_mm(t, still, k_h, window) == pytest.approx(0.0, abs=1e-9)
    creep = 0.0066 + 0.002 * t  # 2 mm/s of creep: not a shake
    assert hold_shake_mm(t, creep, k_h, window) == pytest.approx(0.0, abs=1e-9)
    shake = still + 0.0008 * np.sin(2 * np.pi * 6.0 * t)  # a 1.6 mm peak-to-peak oscillation
    assert 1.5 < hold_shake_mm(t, shake, k_h, window) < 2.0  # the trend takes a little of it
    # new gains at 2.3 s: the probe settles 2 mm nearer the proxy over a few hundred ms (the
    # demo's CI failure: 2.85 mm peak to peak and "not stable", with no oscillation at all)
    k_h2 = np.where(t >= 2.3, 127.0, 43.0)
    moved = 0.0066 - 0.002 * np.clip((t - 2.3) / 0.3, 0.0, 1.0)
    assert np.ptp(moved[t >= 2.0]) * 1000.0 == pytest.approx(2.0)
    assert hold_shake_mm(t, moved, k_h2, window) == pytest.approx(0.0, abs=1e-9)
    # a shake on either side of the change is still seen
    assert hold_shake_mm(t, moved + shake - still, k_h2, window) > 1.0
    # gains changing all the time leave nothing to judge: not a number
    chatter = 43.0 + 10.0 * (np.floor(t / 0.2) % 2)
    assert np.isnan(hold_shake_mm(t, still, chatter, window))
    # but gains scaled to a K_o drifting inside its cell (0.1 % every 50 ms patch) are judged
    drift = 43.0 * (1.0 + 0.001 * np.floor(t / 0.05))
    assert hold_shake_mm(t, still, drift, window) == pytest.approx(0.0, abs=1e-9)
    assert hold_shake_mm(t, shake, drift, window) > 1.5


def test_b_resting_with_other_gains_is_not_the_baseline() -> None:
    # B's delay rose while it rested: it rendered a quarter-K_o fallback (a lighter rest, a
    # shallower dent) until its checked gains came back 0.6 s before A's press. Compared with
    # the hold under the designed gains, that stretch read as B's side barely moving; only the
    # rest under the gains B renders while A holds, settled, counts
    b, (tl, hold) = telemetry(12.0, onset_s=1.0)
    t = b["t_s"]
    fallback = (t >= 2.5) & (t < tl.contact_s - 0.6)
    b["k_h_n_per_m"] = np.where(fallback, 67.6, 213.9)
    b["force_n"] = np.where(fallback, 0.09, b["force_n"])
    b["force_x_n"] = b["force_n"]
    b["proxy_x_m"] = np.where(fallback, b["proxy_x_m"] - 0.0007, b["proxy_x_m"])  # less dent
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["b_force_at_rest_n"] == pytest.approx(REST_N, abs=2e-3)
    assert c["b_surface_displacement_mm"] == pytest.approx(BULGE_M * 1000.0, abs=0.02)
    assert c["b_feels_a"] is True


def test_b_designed_coupled_gains_during_the_hold_still_have_a_baseline() -> None:
    # B's designed gains for its side coupled to A's press (194 N/m) arrive while A presses and
    # replace the uncoupled ones (214 N/m) it rested with: 9 % apart, they leave B's rest as the
    # baseline (the lower K_h lowers B's force in the hold: it can only hide a rise), reported
    # with both K_h; a quarter-K_o fallback stays out (the test above)
    b, (tl, hold) = telemetry(12.0, onset_s=1.0)
    t = b["t_s"]
    coupled = t >= tl.contact_s + 0.3
    b["k_h_n_per_m"] = np.where(coupled, 194.4, 213.9)
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["baseline"] == "before A's press"
    assert c["b_k_h_at_rest_n_per_m"] == pytest.approx(213.9)
    assert c["b_k_h_during_a_press_n_per_m"] == pytest.approx(194.4)
    assert c["b_force_rise_n"] == pytest.approx(HOLD_N - REST_N, abs=2e-3)
    assert c["b_feels_a"] is True


@pytest.mark.parametrize(("compensated", "baseline"), [(True, "before A's press"), (False, None)])
def test_a_design_replaced_by_the_coupled_class_s_keeps_b_s_rest_as_baseline(
    compensated: bool, baseline: str | None
) -> None:
    """The demo's CI failure: B rested with its uncoupled design (176.4 N/m) and held with the
    coupled class's (146.2 N/m, 17 % apart, which on a fast design worker arrives before A's hold
    ends); every design renders C_h K_h = 1, so B's resting force was 0.281 N under both, but the
    report compared K_h alone and found no rest "with the same gains". With compensation the
    rest counts; the same K_h pair without it (a resting force that does depend on K_h) does not."""
    b, (tl, hold) = telemetry(12.0, onset_s=1.0)
    t = b["t_s"]
    coupled = t >= tl.contact_s + 2.8  # the coupled design arrives in A's hold
    b["k_h_n_per_m"] = np.where(coupled, 146.2, 176.4)
    if compensated:
        b["own_gain_m_per_n"] = 1.0 / b["k_h_n_per_m"]
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["baseline"] == baseline
    if compensated:
        assert c["b_k_h_at_rest_n_per_m"] == pytest.approx(176.4)
        assert c["b_k_h_during_a_press_n_per_m"] == pytest.approx(146.2)
        assert c["b_force_rise_n"] == pytest.approx(HOLD_N - REST_N, abs=2e-3)
        assert c["b_surface_displacement_mm"] == pytest.approx(BULGE_M * 1000.0, abs=0.02)
        assert c["b_feels_a"] is True
    else:
        assert c["b_feels_a"] is None


@pytest.mark.parametrize(
    ("rest", "counts"),
    [
        ("pi", True),  # the same PI coupling: the integral holds the probe theta inside
        ("pi-other-theta", False),  # theta is an offset: 0.5 mm against B's ~2 mm hand depth
        ("p-compensated", False),  # compliance 0 too, but no theta offset: a heavier rest
        ("pi-integral-empty", False),  # an integral at 0 is a P coupling: 1/K_h in series
    ],
)
def test_with_an_integral_the_rest_counts_only_with_the_same_integral_and_theta(
    rest: str, counts: bool
) -> None:
    """A review's finding: an integral carrying force drives the penetration to theta whatever
    K_h, so a PI rest and a compensated P hold (both of compliance 0) rest differently (0.225
    against 0.300 N for one hand), and so do two thresholds."""
    b, (tl, hold) = telemetry(12.0, onset_s=1.0)
    t = b["t_s"]
    at_rest = t < tl.contact_s
    b["k_h_n_per_m"] = np.full_like(t, 421.0)
    b["i_gain_n_per_m_s"] = np.full_like(t, 4214.0)
    b["integral_n"] = np.where(b["in_contact"] > 0, 0.2, 0.0)
    b["theta_m"] = np.full_like(t, 0.0005)
    b["own_gain_m_per_n"] = np.zeros_like(t)
    if rest == "pi-other-theta":
        b["theta_m"] = np.where(at_rest, 0.001, 0.0005)
    elif rest == "p-compensated":
        b["i_gain_n_per_m_s"] = np.where(at_rest, 0.0, 4214.0)
        b["integral_n"] = np.where(at_rest, 0.0, b["integral_n"])
        b["own_gain_m_per_n"] = np.where(at_rest, 1.0 / 421.0, 0.0)
    elif rest == "pi-integral-empty":
        b["integral_n"] = np.where(at_rest, 0.0, b["integral_n"])
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert (c["baseline"] == "before A's press") is counts
    assert (c["b_feels_a"] is True) is counts


def test_the_rest_leaves_out_the_settling_after_any_change_of_gains() -> None:
    # designs with the same steady coupling still hand over with a transfer ramp: B's force is
    # disturbed for a moment, which the rest window must not average in
    b, (tl, hold) = telemetry(12.0, onset_s=1.0)
    t = b["t_s"]
    change = tl.contact_s - 0.4  # the uncoupled design arrives 0.4 s before A touches
    b["k_h_n_per_m"] = np.where(t >= change, 176.4, 213.9)
    b["own_gain_m_per_n"] = 1.0 / b["k_h_n_per_m"]
    bump = (t >= change) & (t < change + 0.2)
    b["force_n"] = np.where(bump, b["force_n"] + 0.1, b["force_n"])
    b["force_x_n"] = b["force_n"]
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["b_force_at_rest_n"] == pytest.approx(REST_N, abs=2e-3)


def test_missed_deadlines_count_the_skipped_periods_after_the_first_second() -> None:
    from haptic_collab.demo_report import missed_per_s

    t = np.arange(0.0, 5.0, 1e-3)
    period = np.full_like(t, 1e-3)
    period[0] = np.nan
    period[500] = 4e-3  # in the first second: start-up, not counted
    period[2000] = 2e-3  # one deadline skipped
    period[3000] = 3.1e-3  # two skipped
    period[3500] = 1.4e-3  # late but within the tolerance: none
    span = t[-1] - t[t > 1.0][0]
    assert missed_per_s(t, period, 1000.0) == pytest.approx(3.0 / span)


@pytest.mark.parametrize(("dip_to_n", "dip"), [(None, 0.0), (0.07, REST_N - 0.07)])
def test_the_report_says_how_far_b_s_force_fell_as_a_arrived(dip_to_n, dip) -> None:
    """B resting should feel only A's push as A arrives. A client that rendered unchecked
    fallback gains when the contacts coupled let B's force fall (0.28 to 0.07-0.11 N in the demo
    before the coupled checks ran ahead of need): the report measures that dip."""
    b, (tl, hold) = telemetry(12.0, onset_s=2.2)
    if dip_to_n is not None:  # 0.2 s of a fallback, 0.1 s after A touches
        w = (b["t_s"] >= tl.contact_s + 0.1) & (b["t_s"] < tl.contact_s + 0.3)
        b["force_n"] = np.where(w, dip_to_n, b["force_n"])
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["b_force_dip_as_a_arrives_n"] == pytest.approx(dip, abs=2e-3)
    assert c["b_force_lowest_as_a_arrives_n"] == pytest.approx(REST_N - dip, abs=2e-3)
    # measured only against a rest before A's press
    late, (tl2, hold2) = telemetry(16.0, onset_s=tl_contact(16.0) - 0.5)
    assert (
        coupling_report(late, tl2, hold2, b_approach_end_s=1.0)["b_force_dip_as_a_arrives_n"]
        is None
    )


def landing(decay_per_s: float, p2p_mm: float, onset_s: float = 1.2, duration_s: float = 30.0):
    """B's telemetry with its probe bouncing as it lands: ``p2p_mm`` peak to peak at 2 Hz,
    decaying at ``decay_per_s`` from B's force coming on (0: a shake that never dies out)."""
    b, (tl, hold) = telemetry(duration_s, onset_s=onset_s)
    t = b["t_s"]
    after = np.clip(t - onset_s, 0.0, None)
    bounce = 0.5e-3 * p2p_mm * np.exp(-decay_per_s * after) * np.sin(2.0 * np.pi * 2.0 * after)
    b["probe_x_m"] = SIDE[0] - 1e-3 + np.where(t >= onset_s, bounce, 0.0)
    b["probe_y_m"] = np.zeros_like(t)
    b["probe_z_m"] = np.zeros_like(t)
    return b, tl, hold


def _rest_p2p_mm(b: dict[str, np.ndarray], settled_s: float, until_s: float) -> float:
    mask = (b["t_s"] >= settled_s) & (b["t_s"] < until_s)
    return largest_p2p(b["t_s"], b["probe_x_m"], mask)[0] * 1000.0


@pytest.mark.parametrize("decay_per_s", [1.1, 1.3])
def test_a_landing_bounce_that_dies_out_at_the_design_margin_is_not_a_shake(decay_per_s) -> None:
    # the box's heavy, loosely held hand bounces 5-7 mm as it lands on the liver ball, on the
    # solid itself as under the product (docs/palpation.md): B's rest is judged once a bounce
    # decaying at the design's margin would be under 1 mm, so such a landing is not "unstable"
    b, tl, hold = landing(decay_per_s, p2p_mm=6.0)
    settled, bounced = landing_settled_s(b, 1.2)
    assert 3.0 < bounced <= 6.0  # its first half second, after the trend
    assert settled > 1.2 + B_SETTLE_S
    assert settled <= 1.2 + 0.5 + np.log(6.0) / MIN_DECAY_RATE_PER_S + 0.01
    assert _rest_p2p_mm(b, settled, tl.contact_s) < STABLE_P2P_MM
    # judged from B_SETTLE_S after its force came on, as before, it would have been
    assert _rest_p2p_mm(b, 1.2 + B_SETTLE_S, tl.contact_s) >= STABLE_P2P_MM
    # the coupling's resting force is measured after the bounce too (its force comes on a
    # little after 1.2 s, above B_FORCE_ON_N)
    c = coupling_report(b, tl, hold, b_approach_end_s=1.0)
    assert c["b_settled_s"] > 1.2 + B_SETTLE_S + 0.5
    assert c["b_landing_p2p_mm"] == pytest.approx(bounced, abs=0.5)
    assert c["rest_window_s"][0] >= c["b_settled_s"]


@pytest.mark.parametrize("decay_per_s", [0.0, 0.3, 0.6])
def test_a_shake_slower_than_the_design_margin_is_still_judged_a_shake(decay_per_s) -> None:
    b, tl, _ = landing(decay_per_s, p2p_mm=6.0)
    settled, _ = landing_settled_s(b, 1.2)
    assert _rest_p2p_mm(b, settled, tl.contact_s) >= STABLE_P2P_MM


def test_a_quiet_landing_settles_after_b_settle_s_as_before() -> None:
    b, _, _ = landing(2.0, p2p_mm=0.4)
    settled, bounced = landing_settled_s(b, 1.2)
    assert 0.2 < bounced <= 0.4
    assert settled == pytest.approx(1.2 + B_SETTLE_S)
    # without the probe's columns nothing is measured, and B settles as before
    plain, _ = telemetry(20.0, onset_s=2.2)
    assert landing_settled_s(plain, 2.2) == (2.2 + B_SETTLE_S, None)
