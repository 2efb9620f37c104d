"""A user alone on the object renders the rest plane the patch carries (shared.gains.rest_plane).

At once (no design to wait for), with the object's stiffness; the simulation's surface with the
design again when another user joins (the patch without a rest plane); and, in a contact
that has rendered a verified plane, only once none has for HOLD_BACK_S (a press crossing between
the two every cycle rang on a stiffening object).
"""

from __future__ import annotations

import numpy as np
import pytest

from haptic_collab.shared.gains.policy import HOLD_BACK_S
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.primitives import make_plane
from haptic_collab.shared.protocol import PlaneModel
from tests.client.test_verified_plane_session import TABLE, _check_planes
from tests.support.sessions import press_patch, welcomed_session

K_O = 300.0
REST = PlaneModel(point=(0.0, 0.0, 0.1), normal=(0.0, 0.0, 1.0))


def _patch(
    tick: int, force_n: float, k_true: float = K_O, *, rest: bool = True, b_o: float = 0.0
) -> str:
    """A patch of a press on a spring of ``k_true`` reported at :data:`K_O`, with the rest plane
    z = 0.1 m when ``rest``; out of contact without a force."""
    return press_patch(
        tick,
        force_n,
        k_true,
        k_o=K_O,
        b_o=b_o,
        rest_plane=REST if rest else None,
        in_contact=force_n > 0.0,
    )


def test_alone_the_first_contact_renders_the_rest_plane_at_once() -> None:
    s = welcomed_session("A", "u1", b_h_max=10.0, gain_table=GainTable())  # nothing designed
    up = s.receive(_patch(1, 1.0), 0.05)
    assert up is not None  # no design, no check to wait for: forces need not stay off
    assert up.rest_plane and up.primitive == make_plane((0.0, 0.0, 0.1), (0.0, 0.0, 1.0))
    # the object's stiffness, the least damper (K_h T / 2 at the session's 1 kHz servo), no
    # integral and no compensation
    assert (up.k_h, up.i_gain, up.own_gain) == (K_O, 0.0, 0.0)
    assert up.b_h == pytest.approx(0.5 * K_O / s.servo_rate_hz)
    assert up.choice is not None and up.choice.verified and not up.choice.fallback
    assert s.rest_plane_patches == 1
    # the design is still asked for, for when another user joins
    assert s.design_wanted is not None


def test_a_damped_object_gets_a_damper_and_a_stiff_one_the_devices_stiffness() -> None:
    s = welcomed_session("A", "u1", b_h_max=10.0, gain_table=TABLE)
    up = s.receive(_patch(1, 1.0, b_o=400.0), 0.05)
    assert up is not None and up.rest_plane and up.b_h > 0.0
    stiff = welcomed_session("A", "u1", max_stiffness_n_per_m=200.0, b_h_max=10.0)
    up = stiff.receive(_patch(1, 1.0), 0.05)
    assert up is not None and up.rest_plane and up.k_h == 200.0


def test_without_the_rest_plane_or_with_it_turned_off_the_design_renders() -> None:
    s = welcomed_session("A", "u1", b_h_max=10.0, gain_table=TABLE)
    s.gain_table.design(s.gain_key(0.0, 0), K_O)
    assert s.receive(_patch(1, 1.0), 0.05).rest_plane
    # another user joins: the patch has no rest plane, the design renders the surface
    up = s.receive(_patch(2, 1.0, rest=False), 0.1)
    assert up is not None and not up.rest_plane
    assert up.primitive.point[2] == pytest.approx(0.1 - 1.0 / K_O + up.own_gain * 1.0)
    off = welcomed_session("A", "u1", b_h_max=10.0, gain_table=TABLE, rest_plane=False)
    up = off.receive(_patch(1, 1.0), 0.05)
    assert up is not None and not up.rest_plane and off.rest_plane_patches == 0


def test_after_a_verified_plane_the_rest_plane_waits_a_while_without_one() -> None:
    s = welcomed_session("A", "u1", b_h_max=10.0, gain_table=TABLE)
    rest_then_plane = []
    for tick in range(1, 41):  # a press between 0.1 and 3.1 N, in contact throughout
        f = float(1.6 - 1.5 * np.cos(2 * np.pi * 0.5 * tick / 20.0))
        up = s.receive(_patch(tick, f), tick / 20.0)
        if s.design_wanted is not None:
            key, k_o = s.design_wanted
            s.gain_table.design(key, k_o)
            s.design_wanted = None
        _check_planes(s)
        rest_then_plane.append(up.rest_plane)
    # the rest plane first; once the own-response check holds the object, its verified plane
    assert rest_then_plane[0] and not rest_then_plane[-1]
    assert s.own_response.verified and s.plane_patches > 0
    # the object yields more under the same force: the plane is withdrawn, and the design (not
    # the rest plane) renders until no verified plane has for HOLD_BACK_S (20 patches at 20 Hz)
    f = float(1.6 - 1.5 * np.cos(2 * np.pi * 0.5 * 40 / 20.0))
    wait = round(HOLD_BACK_S * 20)
    rest = []
    for tick in range(41, 41 + wait + 2):
        up = s.receive(_patch(tick, f, 0.8 * K_O), tick / 20.0)
        _check_planes(s)
        rest.append(up.rest_plane)
    assert not s.own_response.verified
    assert rest == [False] * (wait - 1) + [True] * 3
    # a verified plane again in this contact holds it back again; letting go ends the wait
    s2 = welcomed_session("A", "u1", b_h_max=10.0, gain_table=TABLE)
    for tick in range(1, 41):
        f = float(1.6 - 1.5 * np.cos(2 * np.pi * 0.5 * tick / 20.0))
        up = s2.receive(_patch(tick, f), tick / 20.0)
        _check_planes(s2)
    assert not up.rest_plane
    s2.receive(_patch(41, 0.0), 41 / 20.0)
    up = s2.receive(_patch(42, 0.5), 42 / 20.0)
    assert up.rest_plane and up.k_h == K_O
