"""The FEM solid's dynamics against a full time integration of the same discrete model.

What a user would notice: the first ticks of a press are what the solid does. The modes that
do not settle within a simulation period are stepped; the design's ``B_o`` comes from the first
tick, so a first tick off by a few per cent is a ``B_o`` off by about half (issue 60: 4.000
against 4.113 mm/N on the default liver sphere, ``B_o`` 14.7 where it is about 7.8 N/m).

The reference is Newmark's average-acceleration rule (trapezoidal, unconditionally stable;
Newmark 1959) on the whole model ``M u'' + (alpha M + beta K) u' + K u = F`` with a step of
2 ms, 25 per simulation period (1 ms steps move the result by 2e-4 of the static dent).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from haptic_collab.server.objects.fem import FemParams, FemSolid, settle_frequency
from haptic_collab.server.objects.fem_elements import element_lumped_mass
from haptic_collab.server.objects.mesh import default_balloon

TICKS = 10


def newmark_step_response(solid: FemSolid, b: np.ndarray, ticks: int, per_tick: int) -> np.ndarray:
    """The push-weighted displacement ``b^T u`` [m] of a 1 N step push from rest at the end of
    each of ``ticks`` simulation periods, by Newmark's average acceleration (beta 1/4, gamma
    1/2) with ``per_tick`` steps a period, on the solid's own K and lumped M (free rows)."""
    p = solid.params
    dt = p.sim_period_s / per_tick
    k = solid._k_free
    m = np.repeat(element_lumped_mass(solid.nodes, solid.elements, p.density_kg_m3), 3)[solid._dofs]
    alpha, beta = p.rayleigh_alpha, p.rayleigh_beta
    k_eff = (k * (1.0 + 2.0 * beta / dt) + sp.diags(m * (4.0 / dt**2 + 2.0 * alpha / dt))).tocsc()
    lu = spla.splu(k_eff)
    force = -b  # a push along the inward normal
    u = np.zeros_like(b)
    v = np.zeros_like(b)
    a = force / m
    out = []
    for step in range(ticks * per_tick):
        w = 2.0 / dt * u + v
        rhs = force + m * (4.0 / dt**2 * u + 4.0 / dt * v + a) + alpha * m * w + beta * (k @ w)
        u_new = lu.solve(rhs)
        a_new = 4.0 / dt**2 * (u_new - u) - 4.0 / dt * v - a
        v = v + dt / 2.0 * (a + a_new)
        u, a = u_new, a_new
        if (step + 1) % per_tick == 0:
            out.append(-(b @ u))
    return np.array(out)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("volumes"))


def test_the_first_ticks_of_a_press_are_what_the_whole_solid_does(cache):
    """A liver ball of the default sphere's size (r 0.1 m, its lowest modes near 10 Hz, below
    the 20 Hz simulation rate), pressed at its top by 1 N from rest."""
    ball = default_balloon(0.1, 2)  # the default sphere's shape, a cheaper mesh: P2, 642 shown
    solid = FemSolid(ball, FemParams(), cache_dir=cache)
    assert solid.natural_frequencies_hz[0] < 20.0  # the solid rings within the 20 Hz ticks
    # the modes stepped reach up to where a mode settles within a tick (17.5 Hz here)
    assert solid.natural_frequencies_hz[-1] > 0.9 * settle_frequency(solid.params) / (2 * np.pi)
    key = solid.patch_key([0.0, 0.0, 0.1], normal=[0, 0, 1])
    patch = solid.patch(key)
    b = solid._load_rows([patch])[:, 0]
    reference = newmark_step_response(solid, b, TICKS, per_tick=25)
    dofs = (3 * patch.indices[:, None] + np.arange(3)).ravel()
    weights = (patch.weights[:, None] * patch.normal[None, :]).ravel()
    ours = []
    for _ in range(TICKS):
        solid.step([key], [1.0])
        ours.append(-(weights @ solid.linear_displacement.ravel()[dofs]))
    ours = np.array(ours)
    static = 1.0 / solid.contact_stiffness([key])[0]
    assert abs(ours[0] - reference[0]) <= 0.01 * reference[0]  # the first tick, to 1 %
    assert np.abs(ours - reference).max() <= 0.01 * static  # the ringing that follows
    # B_o is the first tick's: f / (K_o + B_o) is the Newmark run's first-tick dent
    k_o, b_o = solid.contact_stiffness([key])[0], solid.contact_damping([key])[0]
    assert 1.0 / (k_o + b_o) == pytest.approx(reference[0], rel=0.01)


def test_the_modes_stepped_are_those_that_do_not_settle_within_a_tick():
    """20 Hz ticks and the liver's beta 0.01 s: modes below about 17.5 Hz ring past a tick;
    a slower simulation (10 Hz) lets more of them settle; no damping, none."""
    liver = FemParams()
    assert settle_frequency(liver) / (2 * np.pi) == pytest.approx(17.5, abs=0.3)
    slower = FemParams(sim_period_s=0.1)
    assert settle_frequency(slower) < settle_frequency(liver)
    assert settle_frequency(FemParams(rayleigh_beta=0.0)) == np.inf


def test_a_look_ahead_step_is_undone_by_rewind(cache):
    """A direct 1 kHz coupling (tools/landing_reference.py) solves its contact force from where
    the surface would be after a tick with no push, then steps with that force: the look-ahead
    must leave no trace, or the reference's ringing is not the solid's."""
    ball = default_balloon(0.1, 2)
    solid = FemSolid(ball, FemParams(sim_period_s=0.001), cache_dir=cache)
    key = solid.patch_key([0.1, 0.0, 0.0], normal=[1, 0, 0])
    twin = FemSolid(ball, FemParams(sim_period_s=0.001), cache_dir=cache)
    for f in (0.5, 0.5, 0.2):  # both ringing under the same pushes
        solid.step([key], [f])
        twin.step([key], [f])
    mark = solid.checkpoint()
    solid.step([key], [0.0])
    looked = solid.vertices.copy()
    solid.rewind(mark)
    assert np.array_equal(solid.vertices, twin.vertices)
    assert not np.array_equal(looked, twin.vertices)  # the solid was ringing
    for f in (0.3, 0.0, 0.0):
        solid.step([key], [f])
        twin.step([key], [f])
    assert np.allclose(solid.vertices, twin.vertices, rtol=0.0, atol=1e-15)
    with pytest.raises(ValueError, match="not this solid"):
        solid.rewind((mark[0][:1], mark[1], mark[2]))
