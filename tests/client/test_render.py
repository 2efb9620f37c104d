"""The local model rendered at the probe, alone: force, penetration, the proxy holds, the damper.

No device, no safety, no thread: positions in, force along the normal out.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from haptic_collab.client.render import LocalRenderer
from haptic_collab.shared.full_loop import DAMPER_FILTER_S
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate, SurfacePatch
from haptic_collab.shared.primitives import Plane, make_plane, make_sphere

T = 1e-3
K_H = 300.0
HOLD = 10
PLANE = make_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))  # outward +z: depth is -z


def plane_at(depth_m: float) -> Plane:
    """The plane moved ``depth_m`` down (inward)."""
    return make_plane((0.0, 0.0, -depth_m), (0.0, 0.0, 1.0))


def renderer(gain_transfer_s: float = 0.0) -> LocalRenderer:
    return LocalRenderer(
        LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=gain_transfer_s)
    )


def still(rd: LocalRenderer, z: float, ticks: int) -> list[tuple[float, float]]:
    """Render ``ticks`` periods with the probe still at (0, 0, z): (force, penetration) each."""
    out = []
    for _ in range(ticks):
        f, e, *_ = rd.render(0.0, 0.0, z, 0.0, 0.0, 0.0)
        out.append((f, e))
    return out


def test_no_force_before_the_first_patch() -> None:
    rd = renderer()
    f, e, nx, ny, nz, c = rd.render(0.0, 0.0, -0.005, 0.0, 0.0, 0.0)
    assert f == 0.0 and math.isnan(e) and (nx, ny, nz) == (0.0, 0.0, 0.0) and not c
    rd.reset()  # nothing to forget, no error
    assert rd.primitive is None and rd.k_h == 0.0


@pytest.mark.parametrize(
    "normal", [(0.0, 0.0, 1.0), (0.6, 0.0, 0.8), (0.0, -1.0, 0.0)], ids=["z", "tilted", "-y"]
)
def test_plane_5mm_inside_gives_k_h_times_5mm_outward(normal: tuple[float, float, float]) -> None:
    anchor = (0.01, 0.02, 0.03)
    plane = make_plane(anchor, normal)
    x, y, z = (a - 0.005 * n for a, n in zip(anchor, plane.normal, strict=True))
    rd = renderer()
    rd.hand_over(LocalModelUpdate(plane, K_H, 0.0), fresh=True)
    f, e, nx, ny, nz, c = rd.render(x, y, z, 0.0, 0.0, 0.0)
    assert c and e == pytest.approx(0.005)
    assert f == pytest.approx(K_H * 0.005)  # 1.5 N
    assert (nx, ny, nz) == pytest.approx(plane.normal)  # outward, as the vector f * n
    assert (rd.k_h, rd.i_gain, rd.patch) == (K_H, 0.0, LocalModelUpdate(plane, K_H, 0.0))


def test_outside_the_surface_there_is_no_force() -> None:
    rd = renderer()
    rd.hand_over(LocalModelUpdate(PLANE, K_H, 0.0), fresh=True)
    f, e, *_, c = rd.render(0.0, 0.0, 0.002, 0.0, 0.0, 0.0)
    assert f == 0.0 and e == pytest.approx(-0.002) and not c


def test_a_sphere_pushes_radially() -> None:
    rd = renderer()
    rd.hand_over(LocalModelUpdate(make_sphere((0.0, 0.0, 0.0), 0.1), K_H, 0.0), fresh=True)
    f, e, nx, ny, nz, c = rd.render(0.0, 0.096, 0.0, 0.0, 0.0, 0.0)
    assert c and f == pytest.approx(K_H * 0.004) and (nx, ny, nz) == pytest.approx((0, 1, 0))


def test_first_order_hold_slides_the_surface_linearly_over_hold_ticks() -> None:
    rd = renderer()
    rd.hand_over(LocalModelUpdate(PLANE, K_H, 0.0), fresh=True)
    z = -0.005
    assert still(rd, z, 3)[-1][1] == pytest.approx(0.005)
    # the surface moves 2 mm in: the penetration goes 5 -> 3 mm in HOLD equal steps
    rd.hand_over(
        LocalModelUpdate(plane_at(0.002), K_H, 0.0, proxy_hold="foh", hold_ticks=HOLD), fresh=False
    )
    e = [pe for _, pe in still(rd, z, HOLD + 3)]
    expected = [0.005 - 0.002 * k / HOLD for k in range(1, HOLD)] + [0.003] * 4
    assert e == pytest.approx(expected, abs=1e-12)
    f = [pf for pf, _ in still(rd, z, 1)]
    assert f == pytest.approx([K_H * 0.003])


def test_zero_order_hold_and_a_fresh_patch_replace_the_surface_at_once() -> None:
    for hold, fresh in (("zoh", False), ("foh", True)):
        rd = renderer()
        rd.hand_over(LocalModelUpdate(PLANE, K_H, 0.0), fresh=True)
        still(rd, -0.005, 3)
        rd.hand_over(
            LocalModelUpdate(plane_at(0.002), K_H, 0.0, proxy_hold=hold, hold_ticks=HOLD), fresh
        )
        assert still(rd, -0.005, 1)[0][1] == pytest.approx(0.003), (hold, fresh)


def test_a_patch_arriving_mid_slide_slides_on_from_the_blend_reached() -> None:
    rd = renderer()
    rd.hand_over(LocalModelUpdate(PLANE, K_H, 0.0), fresh=True)
    z = -0.005
    still(rd, z, 3)
    rd.hand_over(
        LocalModelUpdate(plane_at(0.002), K_H, 0.0, proxy_hold="foh", hold_ticks=HOLD), False
    )
    e1 = [pe for _, pe in still(rd, z, HOLD // 2)]  # half way: 4 mm
    assert e1[-1] == pytest.approx(0.004)
    # jitter: the next surface (4 mm in, penetration 1 mm) arrives before the slide is over
    rd.hand_over(
        LocalModelUpdate(plane_at(0.004), K_H, 0.0, proxy_hold="foh", hold_ticks=HOLD), False
    )
    e2 = [pe for _, pe in still(rd, z, HOLD + 2)]
    # from 4 mm (where it was), not from the 3 mm target: linear, HOLD steps, no jump
    expected = [0.004 - 0.003 * k / HOLD for k in range(1, HOLD)] + [0.001] * 3
    assert e2 == pytest.approx(expected, abs=1e-12)


def test_the_probe_damper_adds_b_h_times_the_filtered_depth_rate_in_contact_only() -> None:
    b_h = 5.0
    v = 0.01  # 10 mm/s inward
    rd = renderer()
    rd.hand_over(LocalModelUpdate(PLANE, K_H, 0.0, b_h=b_h), fresh=True)
    z = -0.001
    f = e = 0.0
    for _ in range(200):  # 40 filter time constants: u has settled to v
        z -= v * T
        f, e, *_ = rd.render(0.0, 0.0, z, 0.0, 0.0, -v * T)
    assert rd.damper_velocity_m_s == pytest.approx(v, rel=1e-6)
    assert f == pytest.approx(K_H * e + b_h * v, rel=1e-6)
    # first tick of motion: u is one filter step of v
    rd2 = renderer()
    rd2.hand_over(LocalModelUpdate(PLANE, K_H, 0.0, b_h=b_h), fresh=True)
    f1, e1, *_ = rd2.render(0.0, 0.0, -0.001, 0.0, 0.0, -v * T)
    assert f1 == pytest.approx(K_H * e1 + b_h * v * T / (T + DAMPER_FILTER_S))
    # out of contact, moving out fast: no pull
    f_out, _, *_, c = rd2.render(0.0, 0.0, 0.001, 0.0, 0.0, 0.002)
    assert f_out == 0.0 and not c


def test_a_gain_change_in_contact_is_carried_off_without_a_step() -> None:
    rd = renderer(gain_transfer_s=0.02)
    rd.hand_over(LocalModelUpdate(PLANE, K_H, 0.0), fresh=True)
    f_before = still(rd, -0.005, 5)[-1][0]
    rd.hand_over(LocalModelUpdate(PLANE, 2 * K_H, 0.0), fresh=False)
    f = [pf for pf, _ in still(rd, -0.005, 40)]
    assert f[0] == pytest.approx(f_before, rel=0.1)  # no jump to 2 * K_H * e
    assert f[-1] == pytest.approx(2 * K_H * 0.005)  # the new gain after the transfer
    # without a transfer time the force steps as eq. 12 says
    rd2 = renderer()
    rd2.hand_over(LocalModelUpdate(PLANE, K_H, 0.0), fresh=True)
    still(rd2, -0.005, 5)
    rd2.hand_over(LocalModelUpdate(PLANE, 2 * K_H, 0.0), fresh=False)
    assert still(rd2, -0.005, 1)[0][0] == pytest.approx(2 * K_H * 0.005)


def test_reset_forgets_the_integral() -> None:
    rd = renderer()
    rd.hand_over(LocalModelUpdate(PLANE, K_H, 1000.0), fresh=True)
    still(rd, -0.005, 100)
    assert rd.model.integral_n > 0.0
    rd.reset()
    assert rd.model.integral_n == 0.0


def pushed(force_n: float) -> SurfacePatch:
    """The server's surface 1 mm deformed, after it applied ``force_n`` [N] from this user."""
    return replace(SurfacePatch.of(plane_at(0.001), K_H), own_force_n=force_n)


def _compensated(force_n: float, c_h: float = 1.0 / K_H) -> LocalModelUpdate:
    """The plane a 1 mm deformation away, moved back out by C_h F_s (as from_wire builds it)."""
    return LocalModelUpdate(
        plane_at(0.001 - c_h * force_n), K_H, 0.0, own_gain=c_h, surface=pushed(force_n)
    )


def test_own_force_compensation_carries_the_own_force_past_the_continuous_force() -> None:
    # a probe resting on the deformed surface: the compensation alone holds the force F_s, also
    # above the integral's limit (the continuous force): capping it there left the excess to an
    # uncompensated loop the design does not check (a FEM torus oscillated at 10 Hz)
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, integral_limit_n=1.75))
    rd.hand_over(_compensated(1.0), fresh=True)
    assert still(rd, -0.001, 1)[0][0] == pytest.approx(1.0)
    assert rd.own_offset_m == pytest.approx(1.0 / K_H)
    rd.hand_over(_compensated(3.0), fresh=False)
    assert still(rd, -0.001, 1)[0][0] == pytest.approx(3.0)
    assert rd.own_offset_m == pytest.approx(3.0 / K_H)


def test_own_force_compensation_stops_at_the_peak_force() -> None:
    # an own force beyond what the device can display (a hostile or broken server) moves the
    # rendered surface out by at most C_h times the peak force
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T), own_force_limit_n=7.9)
    rd.hand_over(_compensated(50.0), fresh=True)
    assert rd.own_offset_m == pytest.approx(7.9 / K_H)
    assert still(rd, -0.001, 1)[0][0] == pytest.approx(7.9)
    with pytest.raises(ValueError, match="own_force_limit_n"):
        LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T), own_force_limit_n=0.0)


def test_compensation_takes_over_an_integral_without_a_step_and_without_keeping_it() -> None:
    rd = renderer(gain_transfer_s=0.05)
    rd.hand_over(LocalModelUpdate(PLANE, K_H, 2000.0), fresh=True)  # a PI press, 5 mm in
    still(rd, -0.005, 300)
    f_before = still(rd, -0.005, 1)[0][0]
    s_before = rd.model.integral_n
    assert s_before > 0.5
    # compensated P gains arrive (no force applied yet, so the same plane): the integral goes
    # to the transfer force and fades
    rd.hand_over(LocalModelUpdate(PLANE, K_H, 0.0, own_gain=1.0 / K_H), fresh=False)
    assert rd.model.integral_n == 0.0
    f = [pf for pf, _ in still(rd, -0.005, 100)]
    assert f[0] == pytest.approx(f_before, rel=0.05)  # no step
    assert f[-1] == pytest.approx(K_H * 0.005)  # and no integral kept beside the new model


def test_withdrawn_compensation_slides_the_surface_in_instead_of_dropping_the_force() -> None:
    # the compensated probe rests on the object's own surface; gains without compensation (a
    # new coupling's unverified fallback) put the rendered surface right there: as a step the
    # contact ended on the next tick and the 1 N with it, now the surface slides in over the
    # transfer time and the force comes down at most F / (transfer ticks) per tick
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.05))
    rd.hand_over(_compensated(1.0), fresh=True)
    f_before = still(rd, -0.001, 5)[-1][0]
    assert f_before == pytest.approx(1.0)
    rd.hand_over(LocalModelUpdate(plane_at(0.001), K_H / 2, 0.0, surface=pushed(1.0)), fresh=False)
    f = [pf for pf, _ in still(rd, -0.001, 80)]
    assert f[0] == pytest.approx(f_before, rel=0.05)
    assert max(abs(b - a) for a, b in zip([f_before, *f], f, strict=False)) <= 1.0 / 50 + 1e-9
    assert f[-1] == pytest.approx(0.0, abs=1e-9)  # then the probe is on the surface: no force
    # and back, the probe 0.1 mm in: compensation restored slides the surface out again
    f_in = still(rd, -0.0011, 5)[-1][0]
    rd.hand_over(_compensated(1.0), fresh=False)
    f = [pf for pf, _ in still(rd, -0.0011, 80)]
    assert f[0] == pytest.approx(f_in, abs=0.03)
    assert max(abs(b - a) for a, b in zip([f_in, *f], f, strict=False)) <= 1.1 / 50 + 1e-9
    assert f[-1] == pytest.approx(1.0 + K_H * 0.0001)


def test_the_compensation_slide_ends_on_time_whatever_patches_arrive_meanwhile() -> None:
    # patches with the same gains arrive every 10 ticks during a 50-tick slide: the slide still
    # ends after 50 ticks (linear), not stretched into an exponential by each patch
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.05))
    rd.hand_over(_compensated(1.0), fresh=True)
    still(rd, -0.0011, 5)
    plain = LocalModelUpdate(plane_at(0.001), K_H, 0.0, surface=pushed(1.0))
    rd.hand_over(plain, fresh=False)
    f = []
    for _ in range(6):
        f += [pf for pf, _ in still(rd, -0.0011, 10)]
        rd.hand_over(plain, fresh=False)
    assert f[48] > f[50] == pytest.approx(K_H * 0.0001)  # the slide is over after 50 ticks


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_new_gains_with_their_own_compensation_keep_a_held_press_steady_whatever_the_hold(
    hold: str,
) -> None:
    # a probe held on the object's surface, 3 N rendered by K_h 580 N/m with C_h K_h = 1; the
    # next cell's design (K_h 67 N/m, C_h K_h = 1, as neighbouring cells of the stiffening
    # object at 300 N/m, 50 Hz) renders the same 3 N once handed over. With a first-order hold
    # the slide over the simulation period carried the change of C_h while the transfer force
    # still carried the K_h step: the force rose to 5.45 N in 20 ms, the probe still, and the
    # stiff grips of the box rang at 3.7-12.7 mm. Either hold now stays at the held force
    F, n = 3.0, 20
    surface = replace(SurfacePatch.of(plane_at(0.001), 500.0), own_force_n=F)

    def design(k_h: float, proxy_hold: str) -> LocalModelUpdate:
        c_h = 1.0 / k_h
        return LocalModelUpdate(
            plane_at(0.001 - c_h * F), k_h, 0.0, own_gain=c_h, surface=surface,
            proxy_hold=proxy_hold, hold_ticks=n,
        )  # fmt: skip

    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.25))
    rd.hand_over(design(580.0, "zoh"), fresh=True)
    assert still(rd, -0.001, 5)[-1][0] == pytest.approx(F)
    rd.hand_over(design(67.0, hold), fresh=False)
    f = [pf for pf, _ in still(rd, -0.001, 400)]
    assert max(abs(pf - F) for pf in f) < 0.01 * F
    # and back to the stiffer design
    rd.hand_over(design(580.0, hold), fresh=False)
    f = [pf for pf, _ in still(rd, -0.001, 400)]
    assert max(abs(pf - F) for pf in f) < 0.01 * F


def _compensated_design(
    k_h: float, force_n: float, depth_m: float, proxy_hold: str = "zoh", n: int = 20
) -> LocalModelUpdate:
    """C_h = 1 / K_h: the surface ``depth_m`` deformed by ``force_n``, moved back out by C_h F_s."""
    surface = replace(SurfacePatch.of(plane_at(depth_m), 500.0), own_force_n=force_n)
    return LocalModelUpdate(
        plane_at(depth_m - force_n / k_h), k_h, 0.0, own_gain=1.0 / k_h, surface=surface,
        proxy_hold=proxy_hold, hold_ticks=n,
    )  # fmt: skip


def test_a_new_design_steps_the_force_as_it_would_itself_at_the_new_own_force() -> None:
    # a 500 N/m spring pressed with 2 N, rendered by K_h 250 N/m; the next patch brings the
    # object's K_h = K_o design and the surface under 3 N. The change of C_h slides in at the
    # last patch's 2 N: the change of F_s is the new design's to render, and with K_h = K_o its
    # surface and compensation move together, so a probe held still feels no step. Taken at the
    # new 3 N the old C_h rendered that 1 N change: 2 N -> 3 N in one tick, then back
    k_o, f1, f2 = 500.0, 2.0, 3.0
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.25))
    rd.hand_over(_compensated_design(250.0, f1, f1 / k_o), fresh=True)
    z = -f1 / k_o  # the probe resting on the deformed surface
    assert still(rd, z, 5)[-1][0] == pytest.approx(f1)
    rd.hand_over(_compensated_design(k_o, f2, f2 / k_o), fresh=False)
    f = [pf for pf, _ in still(rd, z, 400)]
    assert max(abs(pf - f1) for pf in f) < 0.01 * f1


def test_compensated_designs_arriving_mid_slide_keep_a_held_press_steady() -> None:
    # first-order-hold patches every 7 ticks of a 20-tick slide, each another design (C_h K_h =
    # 1): each slide starts from the blend reached, the change of C_h kept out of it, and the
    # K_h step of the slide's pending decrement is carried off too (without it: up to 3.2 N)
    F = 3.0
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.25))
    rd.hand_over(_compensated_design(580.0, F, 0.001), fresh=True)
    still(rd, -0.001, 5)
    f = []
    for k_h in (67.0, 934.0, 200.0, 580.0, 67.0, 400.0):
        rd.hand_over(_compensated_design(k_h, F, 0.001, "foh"), fresh=False)
        f += [pf for pf, _ in still(rd, -0.001, 7)]
    f += [pf for pf, _ in still(rd, -0.001, 300)]
    assert max(abs(pf - F) for pf in f) < 0.01 * F


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_a_probe_leaving_during_the_slide_is_not_pushed_again(hold: str) -> None:
    # C_h rose (580 -> 67 N/m, C_h K_h = 1): the slide holds the surface back, and the probe is
    # withdrawn at 0.5 m/s meanwhile. Dropped with the contact, the slide put the surface tens
    # of mm out at once, into the retreating probe: 2.53 N, 0, then 2.46 N again
    F = 3.0
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.25))
    rd.hand_over(_compensated_design(580.0, F, 0.001), fresh=True)
    still(rd, -0.001, 5)
    rd.hand_over(_compensated_design(67.0, F, 0.001, hold), fresh=False)
    z, f = -0.001, []
    for _ in range(300):
        z_next = z + 0.5 * T
        f.append(rd.render(0.0, 0.0, z_next, 0.0, 0.0, z_next - z)[0])
        z = z_next
    left = next(i for i, pf in enumerate(f) if pf == 0.0)
    assert max(f[left:]) == 0.0


def test_two_patches_between_ticks_keep_a_held_press_steady() -> None:
    # the JS client's worker hands over every queued patch before its next tick: the second
    # change of C_h took the first one's step of the surface for the slide's pending decrement
    # and carried a K_h step of it off (a held 3 N rose to 16 N)
    F = 3.0
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.25))
    rd.hand_over(_compensated_design(580.0, F, 0.001), fresh=True)
    still(rd, -0.001, 5)
    rd.hand_over(_compensated_design(67.0, F, 0.001, "foh"), fresh=False)
    rd.hand_over(_compensated_design(400.0, F, 0.001), fresh=False)
    f = [pf for pf, _ in still(rd, -0.001, 300)]
    assert max(abs(pf - F) for pf in f) < 0.01 * F


def test_a_probe_coming_back_meets_the_surface_where_it_is() -> None:
    # C_h rose (580 -> 67 N/m) and the probe left at 0.5 m/s; then the object, released, is at
    # rest (F_s = 0) and the probe comes back at 0.1 m/s. The slide that held the surface back
    # holds it no further back than the probe has gone: kept whole, the probe met the surface
    # 1.3 mm deep
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.25))
    rd.hand_over(_compensated_design(580.0, 3.0, 0.001), fresh=True)
    still(rd, -0.001, 5)
    rd.hand_over(_compensated_design(67.0, 3.0, 0.001), fresh=False)
    z = -0.001
    for _ in range(40):
        rd.render(0.0, 0.0, z + 0.5 * T, 0.0, 0.0, 0.5 * T)
        z += 0.5 * T
    rd.hand_over(_compensated_design(67.0, 0.0, 0.0), fresh=False)  # at rest, z = 0
    f = 0.0
    for _ in range(1000):
        f, *_ = rd.render(0.0, 0.0, z - 0.1 * T, 0.0, 0.0, -0.1 * T)
        z -= 0.1 * T
        if f > 0.0:
            break
    assert f > 0.0 and -z < 2e-4  # the first force within 0.2 mm of the object's surface


def test_a_rise_of_compensation_out_of_contact_does_not_jump_into_the_probe() -> None:
    # the probe has just left a 3 N press (580 N/m, C_h K_h = 1) by 0.8 mm when the next cell's
    # design (67 N/m) arrives, its F_s still the delayed 3 N: its surface is 39 mm further out.
    # It used to land there at once, 38.8 mm into the probe (2.6 N in one tick); now it comes
    # out no faster than the slide
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.25))
    rd.hand_over(_compensated_design(580.0, 3.0, 0.001), fresh=True)
    still(rd, -0.001, 5)
    z = -0.001 + 3.0 / 580.0 + 0.0008  # 0.8 mm outside the compensated surface
    assert still(rd, z, 3)[-1][0] == 0.0
    rd.hand_over(_compensated_design(67.0, 3.0, 0.001), fresh=False)
    f = [pf for pf, _ in still(rd, z, 300)]
    assert f[0] < 0.02
    assert max(abs(b - a) for a, b in zip(f, f[1:], strict=False)) < 0.02


def test_patches_between_ticks_add_up_to_the_newest_one_alone() -> None:
    # two patches before one tick, each with its own C_h and F_s: the first was never rendered,
    # so the change of C_h is taken at the F_s of the patch the last tick rendered, and the two
    # render as the newest alone would (the first's F_s: 1.55 N went to 8.9 N in one tick)
    def run(patches: list[LocalModelUpdate]) -> list[float]:
        rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.25))
        rd.hand_over(_compensated_design(580.0, 3.0, 0.001), fresh=True)
        still(rd, -0.001, 5)
        for p in patches:
            rd.hand_over(p, fresh=False)
        return [pf for pf, _ in still(rd, -0.001, 300)]

    newest = _compensated_design(580.0, 5.0, 0.001)
    both = run([_compensated_design(67.0, 4.0, 0.001), newest])
    assert both == pytest.approx(run([newest]), abs=1e-9)


def _rest(k_h: float, force_n: float, depth_m: float = 0.001) -> LocalModelUpdate:
    """The rest plane (z = 0) of a surface ``depth_m`` deformed by ``force_n`` [N] from this user,
    rendered with ``k_h`` and no compensation (ClientSession's rendering of a user alone)."""
    surface = replace(
        SurfacePatch.of(plane_at(depth_m), K_H), own_force_n=force_n, rest_plane=PLANE
    )
    return LocalModelUpdate.from_surface(surface, k_h=k_h, i_gain=0.0, rest=True)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_a_change_to_and_from_the_rest_plane_slides_the_surface_without_a_force_step(
    hold: str,
) -> None:
    # a held press rendered on the deformed surface 1 mm in (the paper's local model without
    # compensation: 0.3 N at 2 mm), handed to the rest plane (another user left): the rest plane
    # puts the probe 3 mm deep, 0.9 N with K_h 300 N/m at once; instead the step slides in
    # over the transfer time, then the rest plane's force holds. And back (another user came)
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.05))
    design = LocalModelUpdate(
        plane_at(0.001), K_H, 0.0, surface=pushed(0.3), proxy_hold=hold, hold_ticks=HOLD
    )
    rd.hand_over(design, fresh=True)
    f_before = still(rd, -0.003, 20)[-1][0]
    assert f_before == pytest.approx(K_H * 0.002)
    rd.hand_over(_rest(K_H, 0.3), fresh=False)
    assert rd.primitive == PLANE
    f = [pf for pf, _ in still(rd, -0.003, 80)]
    assert f[0] == pytest.approx(f_before, rel=0.05)
    steps = [abs(b - a) for a, b in zip([f_before, *f], f, strict=False)]
    assert max(steps) <= K_H * 0.001 / 50 + 1e-9  # the 1 mm step over 50 ticks
    assert f[-1] == pytest.approx(K_H * 0.003)
    rd.hand_over(design, fresh=False)
    f = [pf for pf, _ in still(rd, -0.003, 80)]
    assert f[0] == pytest.approx(K_H * 0.003, rel=0.05)
    assert f[-1] == pytest.approx(K_H * 0.002)
    # without a transfer time the surface steps, as every other change does
    rd2 = renderer()
    rd2.hand_over(design, fresh=True)
    still(rd2, -0.003, 20)
    rd2.hand_over(_rest(K_H, 0.3), fresh=False)
    assert still(rd2, -0.003, 1)[0][0] == pytest.approx(K_H * 0.003)


def test_a_rest_plane_out_of_contact_does_not_jump_into_a_probe_just_outside() -> None:
    # the probe 0.5 mm over the deformed surface, out of contact; the rest plane of a surface
    # that is 1 mm out (another user's push let go) would put the probe 0.5 mm deep at once
    # (0.15 N in one tick): it comes out no faster than the slide, 1 mm over 50 ticks
    rd = LocalRenderer(LocalModelParams(k_h=1.0, servo_period_s=T, gain_transfer_s=0.05))
    rd.hand_over(LocalModelUpdate(plane_at(0.001), K_H, 0.0, surface=pushed(0.0)), fresh=True)
    still(rd, -0.0005, 5)
    out = make_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    surface = replace(SurfacePatch.of(plane_at(0.001), K_H), rest_plane=out)
    rd.hand_over(LocalModelUpdate.from_surface(surface, k_h=K_H, i_gain=0.0, rest=True), False)
    f = [pf for pf, _ in still(rd, -0.0005, 80)]
    assert f[0] == 0.0
    assert max(abs(b - a) for a, b in zip(f, f[1:], strict=False)) <= K_H * 0.001 / 50 + 1e-9
    assert f[-1] == pytest.approx(K_H * 0.0005)
