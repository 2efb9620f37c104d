"""A PI contact is kept while the probe stays within the deformation its integral holds (s/K_o).

The fidelity benchmark found the failure this prevents: on a soft object a PI local model keeps
the penetration near theta, so a small retreat of the hand left the (stale) proxy, the contact
released, the integral ramped out, the hand fell back in: a relaxation limit cycle of millimetres.
"""

from __future__ import annotations

import pytest

from haptic_collab.client.servo import ServoCore
from haptic_collab.shared.local_model import LocalModel, LocalModelParams, ThresholdParams
from tests.support.helpers import ScriptedDevice, plane_at, run, scripted_core


def _pressed(recovery: float) -> LocalModel:
    lm = LocalModel(
        LocalModelParams(
            k_h=50.0,
            i_gain=2000.0,
            threshold=ThresholdParams(mode="fixed", theta_m=1e-3),
            release_time_s=0.1,
            recovery_m_per_n=recovery,
        )
    )
    for _ in range(500):  # held 3 mm in: the integral builds up
        lm.step(3e-3)
    return lm


def test_a_small_retreat_keeps_a_pi_contact_within_its_recovery_band() -> None:
    k_o = 100.0
    held = _pressed(1.0 / k_o)
    s = held.integral_n
    assert s / k_o > 0.5e-3  # the band is wider than the retreat below
    f = held.step(-0.5e-3)  # 0.5 mm outside the stale proxy
    assert held.in_contact
    assert f == pytest.approx(50.0 * -0.5e-3 + s, rel=1e-9)  # eq. 12, linear, still pushing
    # without the band the same retreat releases the contact (the limit cycle's first step)
    old = _pressed(0.0)
    old.step(-0.5e-3)
    assert not old.in_contact
    # beyond the band the contact releases as before (section 5.1's ramp)
    held.step(-(s / k_o) - 1e-3)
    assert not held.in_contact


def test_the_servo_hands_the_patch_stiffness_to_the_local_model() -> None:
    dev = ScriptedDevice(lambda n: -0.003)
    core: ServoCore = scripted_core(dev)
    core.set_patch(plane_at(0.0), 200.0, 1000.0, k_o=400.0)
    run(core, 2)
    assert core.local_model.params.recovery_m_per_n == pytest.approx(1.0 / 400.0)
    with pytest.raises(ValueError, match="k_o"):
        core.set_patch(plane_at(0.0), 200.0, 1000.0, k_o=0.0)
