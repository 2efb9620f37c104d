"""Side-by-side fidelity of rendering schemes for a slow, delayed deformable object (1-D model).

The product's claim (the paper's section 1 and footnote 4) is that an adaptive local model renders
a slow (tens of Hz), delayed simulation stably and stiffly where the usual approaches do not. This
module owns the vectorised multirate simulator that measures it (:func:`simulate`, with
:func:`passivity_step`): it runs every scheme against the same hands, objects, network delays and
trajectories (``haptic bench fidelity``, :mod:`haptic_collab.bench.fidelity`). The cells it runs
are :mod:`haptic_collab.research.fidelity_cases`, the schemes and their tunings
:mod:`haptic_collab.research.fidelity_schemes`, the metrics
:mod:`haptic_collab.research.fidelity_metrics`; their names live there and are imported from
there (this module defines only :func:`simulate` and :func:`passivity_step`).

The 1-D world, along the contact normal, depths in metres (positive into the object):

hand + device (servo rate, exact zero-order hold of the force)
    ``m x'' = -b (x' - y') - k (x - y) - f``: the combined hand and device of
    :class:`shared.full_loop.Hand` holding the probe ``x`` around the user's intended motion ``y``
    (the trajectory); ``f`` [N] is the force the device writes, pushing the probe out. A hand of
    ``None`` is a position source: ``x = y`` (for the felt stiffness).
object (simulation rate)
    an elastic surface of stiffness K_o, unilateral: a force F >= 0 pushes it to ``x_o = F / K_o``
    (eq. 6 with B_o = 0); the other objects of :data:`haptic_collab.research.fidelity_cases.OBJECTS`.
    With another user (:class:`haptic_collab.research.fidelity_cases.OtherUser`) the rest surface
    under the contact moves with the other's press, the object's law about it unchanged.
network
    the same one-way delay ``d`` both ways, on the servo clock: the simulation ticking at servo
    tick ``n`` reads what the servo sent at ``n - d`` (at ``n - d - N // 2`` at the stale end of
    the sampling phase: the client sends its state every half simulation period); what it
    publishes reaches the servo from tick ``n + 1 + d`` (one tick of computation).

Schemes (:func:`haptic_collab.research.fidelity_schemes.peer_renderings` says how each is tuned):

``local-p``, ``local-pi`` (this project)
    the local model of eq. 12 with the product's threshold (eq. 17), release ramp, probe damper,
    proxy hold and, for PI, passivity layer (:mod:`shared.passivity`), gains from the product's own
    full-loop design (:mod:`shared.gains.design`) for the delay the client would measure, its
    verified planes and, alone, its rest plane; the simulation receives the force rendered and
    returns the surface.
``mmt``, ``mmt-id`` (Mitra and Niemeyer 2008)
    a plane with the stiffness the simulation reports (``mmt-id``: the one the product's
    own-response check identifies), capped at the device's, at the server's rest surface while
    the user is alone and at the rest surface the patch implies with another user.
``force-jacobian`` (Cavusoglu and Tendick 2000)
    the simulation's force and its local stiffness about the probe it received, in contact only
    (the probe's position clipped to the surface, no stiffness sent out of contact).
``virtual-coupling`` (Colgate, Stanley and Brown 1995; Adams and Hannaford 1999)
    a spring-damper at the device's Z-width corner to a virtual tool with mass and damping that
    the simulation moves against the object from the probe it receives; rendered while the tool
    touches the object.
``static-local`` (Mark et al. 1996; VRPN ForceDevice's plane)
    a plane at the object's rest surface with the K_o reported at the start, never updated.
``direct``
    the simulation computes the contact force ``K_o max(0, x)`` from the probe position it
    received; the servo holds it (zero-order hold) until the next one.
``direct-tdpa`` (Ryu, Kwon and Hannaford 2004)
    ``direct`` with the time-domain passivity observer and controller at the device port.

Every scheme's force is clamped to the device's maximum force. Nothing here reads a clock, a
socket or a thread: time is the servo tick index.

Why the simulator has its own copy of the local model and of the passivity controller. The
servo side of :func:`simulate` restates :class:`shared.local_model.LocalModel` (eq. 12, eq. 17's
threshold, the release ramp, the recovery band, the integral limit) and :func:`passivity_step`
restates :class:`shared.passivity.PassivityController`, as numpy operations over the whole batch
(4000 cells per call in the benchmark, with the probe damper, proxy holds and own-force
compensation of :mod:`client.render` in the same arrays). The product's classes step one user
with plain floats; calling them per cell costs more than the simulator's whole tick (measured
with 4000 cells: about 1 ms per tick for :func:`simulate`, 1.4-2 ms for the 4000
``LocalModel.step`` calls alone and 2.5-3.6 ms for the ``PassivityController.step`` calls), so
the benchmark would take two to four times as long. The copies are checked against the product's
classes on batches of cells that reach every branch (tests/research/test_fidelity_1d.py:
``test_passivity_step_is_the_products_controller``,
``test_the_local_model_is_the_products_local_model``); the copy of the controller also takes an
uncapped damping (``math.inf``, which :class:`shared.passivity.PassivityParams` refuses) for
``direct-tdpa``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from haptic_collab.research.fidelity_cases import (
    RUNAWAY_M,
    Cell,
    Run,
    RunOptions,
    Trajectory,
    stale_ticks,
    stiffening_depth,
    stiffening_force,
    stiffening_tangent,
)
from haptic_collab.research.fidelity_schemes import DeviceModel, TableGains
from haptic_collab.shared.full_loop import DAMPER_FILTER_S, _hand_zoh
from haptic_collab.shared.gains.own_response import (
    empty_deformation,
    empty_jumps,
    empty_sums,
    identify,
    update_deformation,
    update_jumps,
    update_sums,
)
from haptic_collab.shared.gains.rest_plane import rest_plane_dampers
from haptic_collab.shared.types import FloatArray

__all__ = ["passivity_step", "simulate"]


#: The defaults of :func:`simulate`: the simulated Phantom Desktop, no servo imperfections.
_DEVICE = DeviceModel()
_NO_OPTIONS = RunOptions()


#: Plane cells the simulator keeps a check time for, per contact (gain-table cells 0 to this, at
#: the table's 10 % steps up to 1.1**255 N/m; stiffer ones share the last).
_PLANE_CELLS = 256


def _verified_plane_gains(
    mask: NDArray[np.bool_],
    gains: tuple[FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.bool_]],
    planes: TableGains,
    k_o: FloatArray,
    *,
    sums: FloatArray,
    deform: FloatArray,
    seq_last: NDArray[np.int64],
    ok: NDArray[np.bool_],
    ref: FloatArray,
    start: NDArray[np.int64],
    jumps: FloatArray,
    since: NDArray[np.int64],
    delay_s: FloatArray,
    seq: NDArray[np.int64],
    surface: FloatArray,
    force: FloatArray,
    sim_rate_hz: FloatArray,
) -> tuple[
    tuple[FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.bool_]], NDArray[np.bool_]
]:
    """The gains (K_h, I, B_h, C_h, first-order hold) the client renders for the patches of
    ``mask`` once they have fed its own-response check, and where a verified plane renders, as
    :meth:`client.session.ClientSession._render` does: the check (``sums``, ``deform``
    (:func:`shared.gains.own_response.update_deformation`), ``seq_last``, ``ok``, ``ref``, ``start``
    (the tick it started at) and ``jumps`` (:func:`shared.gains.own_response.update_jumps`), updated in
    place) starts over when the contact ends (a patch without a force from this user), takes the
    patches with that force (the surface's depth ``surface`` [m], ``force`` [N], the K_o
    reported ``k_o`` read as the object's tangent, the time between patches from their ticks
    ``seq``), and where it has verified the object as ``ref`` times the K_o reported (1, or the
    stiffness it identified: :func:`shared.gains.own_response.identify`) and the cell of that stiffness
    has a verified plane (``planes``), that plane scaled to the stiffness replaces ``gains`` from
    ``delay_s`` [s] after the check first verified in that plane cell: 0 where the client has
    checked the plane ahead, in the background (:func:`shared.gains.verified_plane.ahead_cells`), or
    the time its worker takes to check it on arrival. ``planes`` holds each plane as the run
    checked it: against the design of the cell of the K_o reported where that cell is designed,
    alone where it is not, as :meth:`client.session.ClientSession._render` renders it.
    ``since``, shape (B, :data:`_PLANE_CELLS`), holds that tick per plane cell, -1 before: the
    client keeps a checked plane for the session."""
    _own_response_check(
        mask, k_o, sums=sums, deform=deform, seq_last=seq_last, ok=ok, ref=ref, start=start,
        jumps=jumps, seq=seq, surface=surface, force=force, sim_rate_hz=sim_rate_hz,
    )  # fmt: skip
    # the client checks the plane of the stiffness verified once its check first verifies
    # there, in its worker (alone in a cell not designed yet), and keeps it: a plane cell not
    # checked before starts its check time
    k_id = ref * k_o
    pc = np.floor(np.log(k_id) / np.log(planes.ratio) + 1e-12)
    pc = np.clip(pc, 0, _PLANE_CELLS - 1).astype(np.int64)
    rows = np.arange(len(pc))
    first = mask & ok & (since[rows, pc] < 0)
    since[rows[first], pc[first]] = seq[first]
    at = since[rows, pc]
    ready = (at >= 0) & ((seq - at) / sim_rate_hz >= delay_s)
    use = mask & ok & ready & planes.has_cell(k_id)
    if not use.any():
        return gains, use
    plane = planes.gains_and_hold(k_id)
    kg, ig, bg, og, fg = (np.where(use, p, g) for p, g in zip(plane, gains, strict=True))
    return (kg, ig, bg, og, fg), use


def _own_response_check(
    mask: NDArray[np.bool_],
    k_o: FloatArray,
    *,
    sums: FloatArray,
    deform: FloatArray,
    seq_last: NDArray[np.int64],
    ok: NDArray[np.bool_],
    ref: FloatArray,
    start: NDArray[np.int64],
    jumps: FloatArray,
    seq: NDArray[np.int64],
    surface: FloatArray,
    force: FloatArray,
    sim_rate_hz: FloatArray,
) -> None:
    """The client's own-response check (:mod:`shared.gains.own_response`, as
    :meth:`client.session.ClientSession._render` runs it) for the patches of ``mask``, its state
    updated in place (the arguments of :func:`_verified_plane_gains`): it starts over when the
    contact ends (a patch without a force from this user); ``ok`` says where it verifies the
    object, ``ref`` the stiffness it holds the object to over the K_o reported ``k_o``."""
    ended = mask & ~(force > 0.0)
    sums[ended] = 0.0
    deform[ended] = empty_deformation()
    ok[ended] = False
    ref[ended] = 1.0
    start[ended] = -1
    jumps[ended] = empty_jumps()
    seq_last[ended] = -1
    push = mask & (force > 0.0)
    if push.any():
        dt = np.where(seq_last >= 0, (seq - seq_last) / sim_rate_hz, 0.0)
        deform[push] = update_deformation(deform, force_n=force, k_o=k_o)[push]
        u = deform[:, 0]
        new = update_sums(sums, dt_s=dt, surface_m=surface, deformation_m=u)
        sums[push] = new[push]
        seq_last[push] = seq[push]
        start[push & (start < 0)] = seq[push & (start < 0)]
        elapsed = (seq - start) / sim_rate_hz
        jumps[push] = update_jumps(jumps, dt_s=dt, force_n=force)[push]
        got_ok, got_ref = identify(
            sums, k_o, ok, ref, elapsed_s=elapsed, jumps=jumps, newest=(u, surface)
        )
        ok[push] = got_ok[push]
        ref[push] = got_ref[push]


def passivity_step(
    pc_energy: FloatArray,
    pc_fa: FloatArray,
    f_d: FloatArray,
    v: FloatArray,
    *,
    servo_period_s: float,
    max_damping_n_s_per_m: FloatArray | float,
    energy_bias_j: FloatArray | float,
    max_force_n: float,
    on: NDArray[np.bool_] | bool = True,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One tick of the 1-D passivity observer and controller for a batch (Ryu, Kwon and Hannaford
    2004; the difference equations of :mod:`shared.passivity`, reset on release).

    Parameters
    ----------
    pc_energy, pc_fa : (B,) float
        Observed energy E(n-1) [J] and the force applied on the previous tick f_a(n-1) [N].
    f_d : (B,) float
        Force the environment wants ON the handle this tick [N].
    v : (B,) float
        Handle velocity [m/s], backward difference over the tick that just ended.
    servo_period_s, max_damping_n_s_per_m, energy_bias_j, max_force_n
        As :class:`shared.passivity.PassivityParams`; the damping may be per cell, and
        ``math.inf`` (uncapped: only the force clamp limits the controller).
    on : bool or (B,) bool
        Cells whose controller acts (the observer always runs).

    Returns
    -------
    (energy, f_a, dissipated) : (B,) float each
        E(n) [J], the force to apply f_a(n) [N], the energy the damper dissipates this tick [J].
    """
    t = servo_period_s
    energy = pc_energy - pc_fa * v * t
    energy = np.where(f_d == 0.0, 0.0, energy)
    fd = np.clip(f_d, -max_force_n, max_force_n)
    predicted = energy - t * fd * v
    vv = v * v
    deficit = -np.asarray(energy_bias_j) - predicted
    act = (deficit > 0.0) & (vv > 0.0) & np.asarray(on)
    tvv = t * vv
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.minimum(deficit / np.where(tvv > 0.0, tvv, 1.0), max_damping_n_s_per_m)
    alpha = np.where(act, alpha, 0.0)
    fa = fd - alpha * v
    fa_c = np.clip(fa, -max_force_n, max_force_n)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(fa != 0.0, fa_c / np.where(fa != 0.0, fa, 1.0), 1.0)
    dissipated = scale * alpha * vv * t
    return energy, fa_c, dissipated


def _ramp_down(x: FloatArray, step: FloatArray) -> FloatArray:
    """``x`` one tick further on its linear ramp to zero by ``step`` (a transfer force or a
    sliding offset, as the client drives them): 0 once the ramp would cross zero."""
    nxt = x - step
    return np.where((x != 0.0) & (nxt != 0.0) & ((nxt > 0.0) == (x > 0.0)), nxt, 0.0)


def simulate(
    cells: Sequence[Cell],
    *,
    device: DeviceModel = _DEVICE,
    servo_rate_hz: float = 1000.0,
    options: RunOptions = _NO_OPTIONS,
) -> Run:
    """Run a batch of cells side by side at the servo rate (module docstring for the model).

    Parameters
    ----------
    cells : sequence of Cell
        Any mix of schemes, objects, rates, delays, hands and trajectories; the batch runs for
        the longest trajectory.
    device : DeviceModel
    servo_rate_hz : float
    options : RunOptions
        Servo jitter and encoder quantisation (off by default).

    Returns
    -------
    Run

    Raises
    ------
    ValueError
        An empty batch, a rate that does not divide the servo rate, a delay that is not a whole
        number of servo ticks, or a non-positive K_o.
    """
    if not cells:
        raise ValueError("simulate needs at least one cell")
    T = 1.0 / float(servo_rate_hz)
    B = len(cells)
    r = [c.rendering for c in cells]
    n_ratio = np.empty(B, dtype=np.int64)
    d_ticks = np.empty(B, dtype=np.int64)
    for i, c in enumerate(cells):
        q = servo_rate_hz / c.sim_rate_hz
        if not (c.sim_rate_hz > 0.0 and abs(q - round(q)) < 1e-9 and round(q) >= 1):
            raise ValueError(f"servo rate / simulation rate must be whole, got {c.sim_rate_hz!r}")
        dq = c.delay_ms * 1e-3 * servo_rate_hz
        if not (c.delay_ms >= 0.0 and abs(dq - round(dq)) < 1e-9):
            raise ValueError(f"delay must be whole servo ticks >= 0, got {c.delay_ms!r} ms")
        if not (math.isfinite(c.k_o) and c.k_o > 0.0):
            raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {c.k_o!r}")
        n_ratio[i] = round(q)
        d_ticks[i] = round(dq)
    k_o = np.array([c.k_o for c in cells])
    sim_hz = float(servo_rate_hz) / n_ratio
    kind = np.array([x.kind for x in r])
    direct = kind == "direct"
    jac = kind == "jacobian"
    tool = kind == "tool"
    mmt = kind == "mmt"
    mmt_id = mmt & np.array([x.identifies for x in r])
    wall = kind == "wall"
    # alone on the object (the server sends the rest surface), or with another user pressing
    alone = np.array([c.other is None for c in cells])
    others = [c.other for c in cells if c.other is not None]
    any_other = bool(others)
    o_rows = np.flatnonzero(~alone)
    o_bulge = np.array([o.bulge_m for o in others])
    o_start = np.array([o.start_s for o in others])
    o_ramp = np.array([max(o.ramp_s, 1e-12) for o in others])
    o_release = np.array([o.release_s for o in others])
    fed_position = direct | jac | tool  # the simulation receives the probe, not a force
    k_h = np.array([x.k_h for x in r])
    ti = T * np.array([x.i_gain for x in r])
    b_h = np.array([x.b_h for x in r])
    foh = np.array([x.proxy_hold == "foh" for x in r])
    theta_m = np.array([x.theta_m for x in r])
    theta = np.where(ti > 0.0, theta_m, 0.0)
    rel_per_tick = T / np.array([x.release_time_s for x in r])
    recovery = np.where(ti > 0.0, 1.0 / k_o, 0.0)  # [m/N]
    pc_any = np.array([x.passivity for x in r])
    two_port = pc_any & direct & np.array([x.two_port for x in r])
    pc_on = pc_any & ~two_port
    pc_bias = np.array([x.passivity_bias_j for x in r])
    pc_bmax = np.array(
        [
            device.max_damping_n_s_per_m
            if x.passivity_max_damping is None
            else x.passivity_max_damping
            for x in r
        ]
    )
    own = np.array([x.own_gain for x in r])
    # the local models' gains follow the K_o reported through the client's gain table
    follow = (kind == "coupling") & np.array([x.follows_k_o and bool(x.table) for x in r])
    table = TableGains([x.table if f else () for x, f in zip(r, follow, strict=True)])
    # ... and where the own-response check verifies the K_o reported, the verified plane of
    # the cell (client.session: shared.gains.own_response, shared.gains.verified_plane)
    checks = follow & np.array([bool(x.planes) for x in r])
    planes = TableGains([x.planes if c else () for x, c in zip(r, checks, strict=True)])
    # ... and, the user alone, the rest plane where no verified plane renders and none has for
    # rest_hold_back_s in the contact (client.session: shared.gains.rest_plane), at the rest surface
    # (depth 0), with the gains of each patch's K_o and the B_o reported
    rest_on = follow & np.array([x.rest_plane for x in r]) & alone
    b_o_rest = np.array(
        [
            c.obj.reported_b_o(c.k_o, c.sim_rate_hz) if on else 0.0
            for c, on in zip(cells, rest_on, strict=True)
        ]
    )
    rest_now = np.zeros(B, dtype=bool)  # the last patch rendered the rest plane
    proxy_last = np.zeros(B)  # the surface [m] the last tick rendered, before the slide
    plane_seen = np.zeros(B, dtype=bool)  # a verified plane rendered in this contact
    plane_at = np.zeros(B, dtype=np.int64)  # the patch it last rendered for
    hold_back_s = np.array([x.rest_hold_back_s for x in r])
    own_sums = empty_sums((B,))
    own_deform = empty_deformation((B,))  # the deformation the K_o reported predicts
    own_seq = np.full(B, -1, dtype=np.int64)
    own_ok = np.zeros(B, dtype=bool)
    own_ratio = np.ones(B)  # K' / K_o the check holds the object to
    own_start = np.full(B, -1, dtype=np.int64)  # tick the check started at
    own_jumps = empty_jumps((B,))  # the changes of force between its patches
    # tick the check first verified in each plane cell at
    own_since = np.full((B, _PLANE_CELLS), -1, dtype=np.int64)
    plane_delay = np.array([x.plane_delay_s for x in r])
    k_h_now, ti_now, b_h_now = k_h.copy(), ti.copy(), b_h.copy()
    # the client's bumpless change of gains (shared.local_model.LocalModel.set_gains): the force
    # step of new gains in contact is a transfer force b, driven linearly to zero
    transfer_s = np.where(follow, np.array([x.gain_transfer_s for x in r]), 0.0)
    per_tick = T / np.where(transfer_s > 0.0, transfer_s, 1.0)  # share of a step driven off
    b_tr = np.zeros(B)  # transfer force [N]
    b_tr_step = np.zeros(B)  # its decrement per tick [N]
    e_last = np.zeros(B)  # the last tick's penetration [m]
    # ... and each patch rendered with its design's proxy hold; a change of C_h slides in over
    # the transfer time, whatever the hold (client.render.LocalRenderer.hand_over)
    own_now = own.copy()  # C_h of the last patch [m/N]
    off_e = np.zeros(B)  # depth [m] added to the penetration, driven to zero
    off_step = np.zeros(B)
    f_s_last = np.zeros(B)  # F_s [N] the last patch's compensation carried
    off_used = np.zeros(B)  # the slide's depth [m] in the last tick's penetration
    jscale = np.array([x.jacobian_scale for x in r])
    m_t = np.array([x.tool_mass_kg for x in r])
    b_t = np.array([x.tool_damping_n_s_per_m for x in r])
    fmax = float(device.max_force_n)
    a_u = T / (T + DAMPER_FILTER_S)

    # the object (ObjectModel): implicit Euler at the simulation rate, x' = a + c F when linear
    objs = [c.obj for c in cells]
    k1 = k_o * np.array([o.stiffness_error for o in objs])
    k2 = k1 * np.array([o.relax_ratio for o in objs])
    tau = np.array([max(o.relax_time_s, 1e-9) for o in objs])
    m_o = np.array([o.mass_kg for o in objs])
    b_o = np.array([o.damping_n_s_per_m for o in objs])
    nonlin = np.array([o.kind == "stiffening" for o in objs])
    xs = np.array([o.stiffening_m if o.kind == "stiffening" else 1.0 for o in objs])
    h = n_ratio * T
    alpha = tau / (tau + h)  # Maxwell arm: q' = alpha q + (1 - alpha) x'
    D = m_o / h**2 + b_o / h + k1 + k2 * alpha
    xo = np.zeros(B)
    vo = np.zeros(B)
    qo = np.zeros(B)
    # the virtual tool (virtual coupling): position and velocity relative to the rest surface,
    # and the probe position the simulation received last
    xt = np.zeros(B)
    vt = np.zeros(B)
    p_prev = np.full(B, np.nan)

    # hands: exact ZOH of m x'' = -b (x' - y') - k (x - y) - f  (input f - k y - b y')
    src = np.array([c.hand is None for c in cells])
    hm = np.array([1.0 if c.hand is None else c.hand.mass_kg for c in cells])
    hb = np.array([0.0 if c.hand is None else c.hand.damping_n_s_per_m for c in cells])
    hk = np.array([0.0 if c.hand is None else c.hand.stiffness_n_per_m for c in cells])
    n_steps = max(round(c.trajectory.duration_s * servo_rate_hz) for c in cells)
    cols = np.arange(B)
    if options.jitter_s > 0.0:
        # wake-up offsets j_n in J {-1, -1/2, 0, 1/2, 1}: periods T + j_(n+1) - j_n, 9 levels
        levels = [_hand_zoh(hm, hb, hk, T + 0.25 * options.jitter_s * k) for k in range(-4, 5)]
        phis = np.stack([p for p, _ in levels])
        gams = np.stack([g for _, g in levels])
        draws = np.random.default_rng(options.seed).integers(0, 5, size=(n_steps + 1, B))
        level = draws[1:] - draws[:-1] + 4
    else:
        phi, gam = _hand_zoh(hm, hb, hk, T)
    quantum = options.quantum_m

    t = np.arange(n_steps, dtype=np.float64) * T
    Y = np.empty((B, n_steps))
    YD = np.empty((B, n_steps))
    trajs: dict[Trajectory, list[int]] = {}
    for i, c in enumerate(cells):
        trajs.setdefault(c.trajectory, []).append(i)
    for tr, idx in trajs.items():
        y, yd = tr.target(t)
        Y[idx] = y
        YD[idx] = yd
    # impact: the hand is already moving with its intention
    x = Y[:, 0].copy()
    v = YD[:, 0].copy()
    xr_prev = x.copy()

    # servo state
    s = np.zeros(B)  # integral force [N]
    rel_step = np.zeros(B)
    was_contact = np.zeros(B, dtype=bool)
    u = np.zeros(B)  # filtered probe velocity
    p_new = np.zeros(B)  # latest surface received
    p_old = np.zeros(B)  # FOH start
    hold_i = np.zeros(B, dtype=np.int64)
    f_recv = np.zeros(B)  # direct, jacobian: force received
    # mmt, jacobian: stiffness estimate received (the rest value at first); the tool: whether it
    # touches the object (not before the first patch)
    k_recv = np.where(tool, 0.0, k_o)
    x_ref = np.zeros(B)  # jacobian: the probe position the force received belongs to
    v_recv = np.zeros(B)  # tool: the tool velocity received [m/s]
    e_env = np.zeros(B)  # two-port: energy the environment has given back, as received [J]
    e_out = np.zeros(B)  # two-port: energy the port has given the user [J]
    seq_seen = np.zeros(B, dtype=np.int64)
    pc_e = np.zeros(B)
    pc_fa = np.zeros(B)
    # network: ring buffers on the servo clock
    # the force the simulation takes: the last servo tick's of its period, or the first's
    # (Cell.stale_sample: the other end of the sampling phase)
    lag = np.array([stale_ticks(n_ratio[i]) if c.stale_sample else 0 for i, c in enumerate(cells)])
    L = int((d_ticks + lag).max()) + 2
    up = np.zeros((L, B))  # what the servo sent at tick n (force, or probe position)
    # latest (value, stiffness, x_ref or force, energy, surface) published by tick n
    down = np.zeros((L, B, 5))
    down_seq = np.zeros((L, B), dtype=np.int64)
    pub = np.zeros((B, 5))
    pub[:, 1] = k_o
    pub_seq = np.zeros(B, dtype=np.int64)
    # two-port, the simulation's side: the probe it used, its force, the energy given back
    x_used = np.zeros(B)
    f_env = np.zeros(B)
    e_env_out = np.zeros(B)
    runaway = np.zeros(B, dtype=bool)

    # which kinds this batch has, once (the tick skips what none of its cells needs)
    any_jac = bool(jac.any())
    any_pc = bool(pc_on.any())
    any_two_port = bool(two_port.any())
    any_follow = bool(follow.any())
    any_tool = bool(tool.any())
    any_tool_nonlin = bool((tool & nonlin).any())
    any_mmt_id = bool(mmt_id.any())
    all_src = bool(src.all())

    X = np.empty((B, n_steps))
    F = np.empty((B, n_steps))
    for n in range(n_steps):
        # 1. read: the probe, and what arrived from the simulation
        if n > 0:
            x = np.where(src, Y[:, n], x)
        bad = ~np.isfinite(x) | (np.abs(x) > RUNAWAY_M)
        if bad.any():
            runaway |= bad
            x = np.where(bad, np.nan_to_num(np.clip(x, -RUNAWAY_M, RUNAWAY_M)), x)
            v = np.where(bad, 0.0, v)
        xr = np.round(x / quantum) * quantum if quantum > 0.0 else x
        vel = (xr - xr_prev) / T
        k_read = n - 1 - d_ticks
        ok = k_read >= 0
        slot = np.where(ok, k_read, 0) % L
        seq = np.where(ok, down_seq[slot, cols], 0)
        fresh = seq != seq_seen
        if fresh.any():
            got = down[slot, cols]
            # first-order hold starts from wherever the proxy is now
            blend = np.minimum(1.0, (hold_i + 1.0) / n_ratio)
            p_cur = np.where(foh, p_old + (p_new - p_old) * blend, p_new)
            p_old = np.where(fresh, p_cur, p_old)
            proxied = fresh & ~(direct | jac | wall)
            p_new = np.where(proxied, got[:, 0], p_new)
            f_recv = np.where(fresh & (direct | jac), got[:, 0], f_recv)
            k_recv = np.where(fresh & (mmt | jac | follow | tool), got[:, 1], k_recv)
            x_ref = np.where(fresh & jac, got[:, 2], x_ref)
            v_recv = np.where(fresh & tool, got[:, 3], v_recv)
            if any_mmt_id:
                # mmt-id: the client's own-response check on each patch, as the product's
                ident = fresh & mmt_id
                if ident.any():
                    _own_response_check(
                        ident, np.where(ident, k_recv, k_o), sums=own_sums, deform=own_deform, seq_last=own_seq,
                        ok=own_ok, ref=own_ratio, start=own_start, jumps=own_jumps, seq=seq,
                        surface=got[:, 4], force=np.maximum(got[:, 2], 0.0), sim_rate_hz=sim_hz,
                    )  # fmt: skip
                    # with another user the plane is at the rest surface the patch implies with
                    # the stiffness identified (alone, the server's rest surface: published)
                    k_hat = np.where(ident, np.where(own_ok, own_ratio, 1.0) * k_recv, 1.0)
                    implied = got[:, 4] - np.maximum(got[:, 2], 0.0) / k_hat
                    p_new = np.where(ident & ~alone, implied, p_new)
            e_env = np.where(fresh & two_port, got[:, 3], e_env)
            hold_i = np.where(fresh, 0, hold_i + 1)
            seq_seen = seq
            if any_follow:
                re_gain = fresh & follow
                if re_gain.any():
                    # the K_o each local model's patch reports (the other kinds' are not read:
                    # a force-jacobian's or a tool's may be 0)
                    k_recv_f = np.where(follow, k_recv, k_o)
                    kg, ig, bg, og, fg = table.gains_and_hold(k_recv_f)
                    plane_on = np.zeros(B, dtype=bool)
                    # the rest plane's gains for this patch (shared.gains.rest_plane)
                    k_rest, b_rest, _ = rest_plane_dampers(
                        k_recv_f, b_o_rest, sim_hz, device.max_stiffness_n_per_m,
                        device.max_damping_n_s_per_m, servo_period_s=T,
                    )  # fmt: skip
                    if checks.any():
                        (kg, ig, bg, og, fg), plane_on = _verified_plane_gains(
                            re_gain & checks,
                            (kg, ig, bg, og, fg),
                            planes,
                            k_recv_f,
                            sums=own_sums,
                            deform=own_deform,
                            seq_last=own_seq,
                            ok=own_ok,
                            ref=own_ratio,
                            start=own_start,
                            jumps=own_jumps,
                            since=own_since,
                            delay_s=plane_delay,
                            seq=seq,
                            surface=got[:, 4],
                            force=np.maximum(got[:, 2], 0.0),
                            sim_rate_hz=sim_hz,
                        )
                    # the rest plane, alone on the object, where no verified plane renders and
                    # none has for HOLD_BACK_S in this contact (patches with a force from this
                    # user)
                    touching = got[:, 2] > 0.0
                    plane_seen = np.where(re_gain, touching & (plane_seen | plane_on), plane_seen)
                    plane_at = np.where(re_gain & plane_on, seq, plane_at)
                    held = plane_seen & ((seq - plane_at) / sim_hz < hold_back_s)
                    rest_new = re_gain & rest_on & ~plane_on & ~held
                    kg = np.where(rest_new, k_rest, kg)
                    bg = np.where(rest_new, b_rest, bg)
                    ig = np.where(rest_new, 0.0, ig)
                    og = np.where(rest_new, 0.0, og)
                    fg = np.where(rest_new, False, fg)
                    # a change between it and the surface: the step at the probe of what the
                    # old patch renders next and the new one would slides off over the transfer
                    # time, in contact (out of contact only toward the probe), as one slide
                    # without a first-order hold (client.render.LocalRenderer.hand_over)
                    switch = re_gain & (rest_new != rest_now) & (transfer_s > 0.0)
                    rest_now = np.where(re_gain, rest_new, rest_now)
                    f_new = np.maximum(got[:, 2], 0.0)
                    target = np.where(rest_new, 0.0, got[:, 4] - og * f_new)
                    sw_step = target - proxy_last + off_e
                    switch &= was_contact | (sw_step < 0.0)
                    # a change of C_h slides in over the transfer time whatever the hold, at
                    # the last patch's F_s; a first-order hold slides from the old surface with
                    # the new compensation
                    # (out of contact only a rise of C_h, which moves the surface out)
                    slide = re_gain & (was_contact | (og > own_now)) & (transfer_s > 0.0)
                    slide &= (og != own_now) & ~switch
                    pending = off_e - off_used  # the slide's next decrement, already taken
                    c_step = np.where(slide, (own_now - og) * f_s_last, 0.0)
                    off_e = off_e + c_step
                    p_old = np.where(slide & fg, p_old + c_step, p_old)
                    f_s_last = np.where(re_gain, np.maximum(got[:, 2], 0.0), f_s_last)
                    off_step = np.where(slide, off_e * per_tick, off_step)
                    own_now = np.where(re_gain, og, own_now)
                    # the patch's surface moved out by the C_h rendered for it (the client's
                    # SurfacePatch.from_wire; a verified plane's C_h is not the table's)
                    p_new = np.where(re_gain, target, p_new)
                    off_e = np.where(switch, sw_step, off_e)
                    off_used = np.where(switch, sw_step, off_used)
                    off_step = np.where(switch, sw_step * per_tick, off_step)
                    p_old = np.where(switch, p_new, p_old)
                    foh = np.where(re_gain, fg, foh)
                    # the step of K_h e (e with the slide's pending decrement) and of the
                    # damper's B_h u, and, with own-force compensation, the integral force, are
                    # handed to the transfer force
                    step = (k_h_now - kg) * (e_last + pending)
                    step = step + np.where((b_h_now > 0.0) | (bg > 0.0), (b_h_now - bg) * u, 0.0)
                    drop = re_gain & was_contact & (og > 0.0)
                    step = step + np.where(drop, s, 0.0)
                    s = np.where(drop, 0.0, s)
                    go = re_gain & was_contact & (transfer_s > 0.0) & (step != 0.0)
                    go &= np.isfinite(step)
                    b_tr = np.where(go, b_tr + step, b_tr)
                    b_tr_step = np.where(go, b_tr * per_tick, b_tr_step)
                    k_h_now = np.where(re_gain, kg, k_h_now)
                    ti_now = np.where(re_gain, T * ig, ti_now)
                    b_h_now = np.where(re_gain, bg, b_h_now)
                    theta = np.where(ti_now > 0.0, theta_m, 0.0)
                    recovery = np.where(ti_now > 0.0, 1.0 / k_o, 0.0)
        else:
            hold_i = hold_i + 1
        # 2. compute
        w = np.where(foh, np.minimum(1.0, (hold_i + 1.0) / n_ratio), 1.0)
        proxy = p_old + (p_new - p_old) * w
        proxy_last = proxy
        e = xr - proxy
        if any_follow:
            e = e + off_e
            off_used = off_e
            off_e = _ramp_down(off_e, off_step)
        k_hat = np.where(mmt_id & own_ok, own_ratio, 1.0) * k_recv if any_mmt_id else k_recv
        k_eff = np.where(mmt, np.minimum(k_hat, k_h), k_h_now)
        # contact: the probe past the proxy; an integral keeps it while the probe is within the
        # deformation its force holds (s / K_o: the object's surface follows a retreating probe
        # back, the proxy is a stale copy of it; shared.local_model's recovery band)
        contact = (e > 0.0) | (was_contact & (e > -s * recovery))
        # local model, eq. 12 with eq. 17's threshold and the release ramp (shared.local_model),
        # plus the transfer force of a change of gains (this tick's, then driven down; none out
        # of contact)
        if any_follow:
            b_use = np.where(contact, b_tr, 0.0)
            b_tr = np.where(contact, _ramp_down(b_tr, b_tr_step), 0.0)
            # out of contact a slide that deepens the surface ends; one holding it back holds it
            # no further back than the probe has left (client.render.LocalRenderer.render)
            off_e = np.where(contact, off_e, np.minimum(0.0, np.maximum(off_e, off_used - e)))
            f_lm = np.where(contact, np.maximum(k_eff * e + s + b_use, 0.0), s)
        else:
            f_lm = np.where(contact, np.maximum(k_eff * e + s, 0.0), s)
        start_rel = ~contact & (was_contact | (rel_step == 0.0))
        rel_step = np.where(contact, 0.0, np.where(start_rel, s * rel_per_tick, rel_step))
        s = np.where(
            contact,
            np.clip(s + ti_now * (e - theta), 0.0, fmax),
            np.maximum(s - rel_step, 0.0),
        )
        was_contact = contact
        u = u + a_u * (vel - u)
        f_lm = np.where(contact & (b_h_now > 0.0), np.maximum(f_lm + b_h_now * u, 0.0), f_lm)
        f = np.where(direct, f_recv, f_lm)
        if any_jac:
            # force-jacobian: the simulation's force and its local stiffness about x_ref
            f_j = f_recv + np.minimum(jscale * k_recv, k_h) * (xr - x_ref)
            f = np.where(jac, np.where(f_j > 0.0, np.maximum(f_j + b_h * u, 0.0), 0.0), f)
        if any_tool:
            # virtual coupling: the spring-damper to the tool received, while the tool touches
            # the object (k_recv: 1 in contact, 0 out of it), pushing only
            f_c = k_h * (xr - p_new) + b_h * (u - v_recv)
            f = np.where(tool, np.where(k_recv > 0.0, np.maximum(f_c, 0.0), 0.0), f)
        f = np.clip(f, -fmax, fmax)
        # the object is pushed by the coupling, never by the passivity controller's damper (as
        # the client's state: client.servo.ServoCore publishes the force before it)
        f_up = f
        # passivity layer at the device port: force ON the handle is -f, its velocity vel
        if any_pc:
            pc_e, fa, _ = passivity_step(
                pc_e,
                pc_fa,
                -f,
                vel,
                servo_period_s=T,
                max_damping_n_s_per_m=pc_bmax,
                energy_bias_j=pc_bias,
                max_force_n=fmax,
                on=pc_on,
            )
            pc_fa = np.where(pc_on, fa, pc_fa)
            f = np.where(pc_on, -fa, f)
        if any_two_port:
            # two-port, the device's side: give the user no more energy than the environment
            # has given back (as far as it is known here); the power to the user is (-f) vel
            p_last = pc_fa * vel * T
            e_out = e_out + np.where(two_port, np.maximum(p_last, 0.0), 0.0)
            want = np.maximum(-f * vel * T, 0.0)
            deficit = e_out + want - e_env - pc_bias
            vv = vel * vel
            act = two_port & (deficit > 0.0) & (vv > 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                damp = np.where(act, deficit / np.where(vv > 0.0, vv * T, 1.0), 0.0)
            f_tp = np.clip(f + damp * vel, -fmax, fmax)
            f = np.where(two_port, f_tp, f)
            pc_fa = np.where(two_port, -f, pc_fa)
        X[:, n] = xr
        F[:, n] = f
        if any_follow:
            e_last = np.where(np.isfinite(e), e, -1.0)
        # 3. write: the hand moves under the force held over the tick
        if not all_src:
            if options.jitter_s > 0.0:
                phi = phis[level[n], cols]
                gam = gams[level[n], cols]
            inp = f - hk * Y[:, n] - hb * YD[:, n]
            xn = phi[:, 0, 0] * x + phi[:, 0, 1] * v + gam[:, 0] * inp
            vn = phi[:, 1, 0] * x + phi[:, 1, 1] * v + gam[:, 1] * inp
            x = np.where(runaway, x, xn)
            v = np.where(runaway, 0.0, vn)
        xr_prev = xr
        # uplink, then the simulation's tick
        up[n % L] = np.where(fed_position, xr, np.where(pc_on, f_up, f) if any_pc else f)
        sim_now = (n % n_ratio) == 0
        if sim_now.any():
            k_up = n - d_ticks - lag
            slot_up = np.where(k_up >= 0, k_up, 0) % L
            got = np.where(k_up >= 0, up[slot_up, cols], 0.0)
            # another user moves the rest surface under this contact (OtherUser): the object's
            # state is kept relative to it, what it publishes is absolute
            rest = np.zeros(B)
            if any_other:
                u_on = np.clip((n * T - o_start) / o_ramp, 0.0, 1.0)
                u_off = np.clip((n * T - o_release) / o_ramp, 0.0, 1.0)
                on = 10 * u_on**3 - 15 * u_on**4 + 6 * u_on**5
                off = 10 * u_off**3 - 15 * u_off**4 + 6 * u_off**5
                rest[o_rows] = -o_bulge * (on - off)
            got_rel = np.where(fed_position, got - rest, got)
            a = (m_o * (xo + h * vo) / h**2 + b_o * xo / h + k2 * alpha * qo) / D
            # a force pushes the object (the local models, MMT, the wall)
            f_in = np.maximum(got_rel, 0.0)
            x_f = np.where(nonlin, stiffening_depth(k1, xs, f_in), a + f_in / D)
            # the probe position drives it (direct, force-jacobian): the surface put at the probe
            # where the probe is in it, else where the object is (x_s clipped to the surface)
            contact = np.where(nonlin, got_rel > 0.0, got_rel > a)
            x_in = np.clip(got_rel, 0.0, RUNAWAY_M)
            f_p = np.where(
                nonlin,
                stiffening_force(k1, xs, x_in),
                np.where(contact, (got_rel - a) * D, 0.0),
            )
            x_p = np.where(nonlin, x_in, np.where(contact, got_rel, a))
            if any_two_port:
                # two-port, the simulation's side: the energy the object has given back
                de = 0.5 * (f_env + f_p) * (x_p - x_used)
                e_env_out = np.where(
                    two_port & sim_now, e_env_out + np.maximum(-de, 0.0), e_env_out
                )
                x_used = np.where(two_port & sim_now, x_p, x_used)
                f_env = np.where(two_port & sim_now, f_p, f_env)
            x_new = np.where(fed_position, x_p, x_f)
            f_obj = np.where(fed_position, f_p, f_in)
            touch = contact
            if any_tool:
                # the virtual tool (mass m_t, damping b_t to ground) pulled by the coupling
                # (K_c, B_c) toward the probe received, against the object: implicit Euler at
                # the simulation rate, the tool and the object's surface one point in contact.
                # The coupling on the tool is K_c (p - z) + B_c (p' - (z - x_t) / h) = Kc (p_c
                # - z); the tool's inertia and damping are M (z - a_t), as the object's D (z - a)
                pd = np.where(np.isfinite(p_prev), (got_rel - p_prev) / h, 0.0)
                p_prev = np.where(sim_now & tool, got_rel, p_prev)
                big_m = m_t / h**2 + b_t / h
                a_t = np.where(
                    big_m > 0.0,
                    (m_t * (xt + h * vt) / h**2 + b_t * xt / h) / np.maximum(big_m, 1e-300),
                    0.0,
                )
                kc = np.where(tool, k_h + b_h / h, 1.0)
                p_c = (k_h * got_rel + b_h * pd + b_h * xt / h) / kc
                z_free = (big_m * a_t + kc * p_c) / (big_m + kc)
                k_tot = big_m + kc
                z_lin = (big_m * a_t + kc * p_c + D * a) / (k_tot + D)
                t_touch = np.where(nonlin, z_free > 0.0, z_free > a)
                z_t = np.where(t_touch, z_lin, z_free)
                f_t = np.where(t_touch, D * (z_lin - a), 0.0)
                if any_tool_nonlin:
                    zp = np.maximum(z_free, 0.0)
                    z = k_tot * zp / (k_tot + k1)
                    for _ in range(8):  # Newton on the convex, increasing F(z) + K (z - z_free)
                        z = z - (stiffening_force(k1, xs, z) + k_tot * (z - zp)) / (
                            stiffening_tangent(k1, xs, z) + k_tot
                        )
                    z = np.clip(z, 0.0, zp)
                    z_t = np.where(nonlin, np.where(t_touch, z, z_free), z_t)
                    f_t = np.where(nonlin & t_touch, stiffening_force(k1, xs, z), f_t)
                x_new = np.where(tool, np.where(t_touch, z_t, x_f), x_new)
                f_obj = np.where(tool, f_t, f_obj)
                touch = np.where(tool, t_touch, touch)
                upd_t = sim_now & tool & ~runaway
                vt = np.where(upd_t, (z_t - xt) / h, vt)
                xt = np.where(upd_t, z_t, xt)
            upd = sim_now & ~runaway
            vo = np.where(upd, (x_new - xo) / h, vo)
            qo = np.where(upd, alpha * qo + (1.0 - alpha) * x_new, qo)
            xo = np.where(upd, x_new, xo)
            # what the simulation publishes: its stiffness estimate is the object's tangent
            # stiffness as it believes it (off by the object's stiffness error)
            k_est = np.where(nonlin, stiffening_tangent(k_o, xs, np.maximum(xo, 0.0)), k_o)
            # own-force compensation of a local model that follows the reported K_o: the C_h
            # its client renders for it
            own_eff = np.where(follow, table.gains(k_est)[3], own) if any_follow else own
            xo_abs = xo + rest
            val = np.where(
                fed_position & ~tool,
                f_obj,
                np.where(
                    mmt,
                    # alone: the server's rest surface (as the product's rest plane); with
                    # another user the rest surface the simulation estimates
                    np.where(alone, rest, xo_abs - f_obj / k_est),
                    np.where(tool, xt + rest, xo_abs - own_eff * f_obj),
                ),
            )
            # force-jacobian: its stiffness in contact only; the tool: whether it touches
            k_pub = np.where(jac & ~touch, 0.0, np.where(tool, touch.astype(float), k_est))
            col2 = np.where(jac, x_p + rest, got)
            col3 = np.where(tool, vt, e_env_out)
            new = np.stack([val, k_pub, col2, col3, xo_abs], axis=1)
            pub = np.where(sim_now[:, None], new, pub)
            pub_seq = pub_seq + sim_now
        down[n % L] = pub
        down_seq[n % L] = pub_seq
    return Run(t=t, x=X, f=F, runaway=runaway)
