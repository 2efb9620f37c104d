"""The product's own client, with a hand of the box in the loop, on objects drawn from the declared set.

An independent time-domain loop around the code a user runs (docs/stability.md): each user is a
:class:`client.session.ClientSession` fed the ``patch`` frames a server would send (parsed by the
protocol, the keys K_o / K_o_eff / K_o_stiff / B_o / own force / rest plane as
:class:`server.world.World` computes them), a :class:`client.servo.ServoCore` with the servo
configuration ``haptic client`` builds (:func:`servo_setup`), and a :class:`client.devices.sim.SimDevice`
whose hand is the drawn hand of the box. The link's jobs (designs, interim checks, verified
planes) run in this process with the product's own functions and are delivered as a worker
would, after a latency (:data:`JOB_LATENCY_S`); a job whose answer would come after the run
ends is never computed. The server's side is a 1-D object of :mod:`shared.declared_set` stepped
at the simulation rate with the latest force that has arrived, as the server's tick does (Step
3), behind a network with delay and jitter each way.

Not exercised here (stated in docs/stability.md): the server's force bound
(:mod:`server.force_bound`), its recommended gains (the patches carry none: the client's own
table and designs render), the link's checks ahead of need, and the 3-D geometry (the contact is
a plane along one axis).

This module reads no clock: time is the servo tick count.
"""

from __future__ import annotations

import copy
import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from haptic_collab.client.devices.profiles import get_sim_profile
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.gain_store import preload
from haptic_collab.client.servo import ServoCore
from haptic_collab.client.servo_config import ServoConfig
from haptic_collab.client.session import ClientSession, ServoSample
from haptic_collab.client.theta import threshold_for
from haptic_collab.server.contact_stiffness import effective_stiffness, stiff_stiffness
from haptic_collab.shared.declared_set import DrawnCondition, DrawnHand
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.interim import interim_design
from haptic_collab.shared.gains.table import GainTable, design_cell
from haptic_collab.shared.gains.verified_plane import plane_against, verified_plane
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.protocol import (
    DeviceInfo,
    LinkConditions,
    ObjectInfo,
    Patch,
    PlaneModel,
    Pong,
    Welcome,
    encode,
)

SERVO_HZ = 1000.0
T = 1.0 / SERVO_HZ
PROFILE = "phantom-desktop"
#: Seconds from a job's request to its answer, as the link's workers take on a quiet machine
#: (docs/client.md: a design 1-3 s, an interim check 0.1-0.5 s, a plane 0.1-10 s).
JOB_LATENCY_S = {"design": 2.0, "check": 0.3, "plane": 1.0}
#: Seconds of the run: the user presses from ``PRESS_S``, is nudged at ``NUDGE_S``, holds, and
#: lets go at ``RELEASE_S``; a partner presses over ``PARTNER_S``.
PRESS_S = (0.2, 0.6)
NUDGE_S = 0.9
PARTNER_S = (0.4, 1.3)
HOLD_WINDOW_S = (2.8, 4.2)
RELEASE_S = 4.2
DURATION_S = 4.8
#: Probe peak to peak [m] over the hold window, after removing a quadratic trend (creep, the
#: integral's slow catch-up), below which a run counts as stable: the fidelity benchmark's
#: threshold (:data:`haptic_collab.research.fidelity_metrics.STABLE_HOLD_P2P_M`).
STABLE_P2P_M = 0.5e-3
#: A probe this far from the surface [m], or a non-finite one, has run away.
RUNAWAY_M = 0.3

_DESIGNS: dict[tuple[Any, ...], Any] = {}


def _memo(kind: str, fn: Callable[..., Any], *args: Any) -> Any:
    """The product's job function on ``args``, computed once per process (designs are pure)."""
    k = (kind, *args)
    if k not in _DESIGNS:
        try:
            _DESIGNS[k] = fn(*args)
        except ValueError as exc:
            _DESIGNS[k] = exc
    return _DESIGNS[k]


def servo_setup(
    mode: Literal["p", "pi"], sim_rate_hz: float, passivity: Literal["auto", "on", "off"] = "auto"
) -> tuple[ServoConfig, LocalModelParams]:
    """The servo configuration and local-model parameters ``haptic client`` builds for the
    simulated Phantom Desktop (:func:`client.app._local_model_params`, ``_start_servo``)."""
    from haptic_collab.client.app import GAIN_TRANSFER_S, passivity_on

    prof = get_sim_profile(PROFILE)
    lim = prof.limits
    on = passivity_on(passivity, mode)
    lm = LocalModelParams(
        k_h=1.0,
        servo_period_s=T,
        threshold=threshold_for("auto", mode, 0.001, prof.encoder_resolution_m, T),
        release_time_s=2.0 / sim_rate_hz,
        integral_limit_n=lim.max_continuous_force_n or lim.max_force_n,
        gain_transfer_s=GAIN_TRANSFER_S,
    )
    return ServoConfig(servo_rate_hz=SERVO_HZ, passivity=on), lm


class ObjectSim:
    """The server's object along the normals of ``m`` contacts (depth inward positive, [m]).

    A coupled linear spring-damper-mass for the ``spring`` family (stiffness matrix ``r K_nom``,
    ``K_nom`` the inverse of the nominal compliance ``((1 - c) I + c 1 1^T) / K_o``), one contact
    for the other families; stepped by implicit Euler over one simulation period with the force
    held, as a slow simulation does.
    """

    def __init__(self, cond: DrawnCondition) -> None:
        self.cond = cond
        o = cond.obj
        m = cond.users
        c = cond.coupling
        self.h = 1.0 / cond.sim_rate_hz
        self.c_nom = ((1.0 - c) * np.eye(m) + c * np.ones((m, m))) / cond.k_o
        self.k_nom = np.linalg.inv(self.c_nom)
        self.x = np.zeros(m)
        self.v = np.zeros(m)
        self.inner = 0.0  # two-mass: the inner mass's depth
        self.inner_v = 0.0
        self.rest = 0.0  # creep: the rest position
        self.t = 0.0
        self.obj = o

    def stiffness_scale(self) -> float:
        o = self.obj
        if o.family == "drift":
            return o.k_ratio * math.exp(
                o.drift * math.sin(2.0 * math.pi * self.t / o.drift_period_s)
            )
        return o.k_ratio

    def step(self, f: np.ndarray) -> None:
        """One simulation period with the contact forces ``f`` [N] (inward, >= 0) held."""
        o, h = self.obj, self.h
        if o.family == "hunt-crossley":
            self._step_hc(float(f[0]))
        elif o.family == "two-mass":
            self._step_two_mass(float(f[0]))
        else:
            k = self.stiffness_scale() * self.k_nom
            n = len(self.x)
            mm = o.mass_kg * np.eye(n)
            bb = o.damping_n_s_per_m * np.eye(n)
            rest = np.full(n, self.rest)
            a = mm + h * bb + h * h * k
            rhs = mm @ self.v + h * (f - k @ (self.x - rest))
            self.v = np.linalg.solve(a, rhs)
            self.x = self.x + h * self.v
            if o.family == "creep":
                self.rest += (h / o.creep_time_s) * (float(self.x[0]) - self.rest)
        self.t += h

    def _step_two_mass(self, f: float) -> None:
        o, h = self.obj, self.h
        k = o.k_ratio * self.cond.k_o
        s = o.inner_split  # k1 / (k1 + k2); series k1 k2 / (k1 + k2) = k
        k1, k2 = k / (1.0 - s), k / s
        b = o.damping_n_s_per_m
        mm = np.diag([o.mass_kg, o.inner_mass_kg])
        kk = np.array([[k1, -k1], [-k1, k1 + k2]])
        bb = np.array([[b, -b], [-b, 2.0 * b]])
        x = np.array([self.x[0], self.inner])
        v = np.array([self.v[0], self.inner_v])
        a = mm + h * bb + h * h * kk
        v = np.linalg.solve(a, mm @ v + h * (np.array([f, 0.0]) - kk @ x))
        x = x + h * v
        self.x[0], self.inner = float(x[0]), float(x[1])
        self.v[0], self.inner_v = float(v[0]), float(v[1])

    def hc_k(self) -> float:
        """Hunt-Crossley ``k`` such that the tangent at the press's depth is ``r K_o``."""
        o, cond = self.obj, self.cond
        kt = o.k_ratio * cond.k_o
        n = o.exponent
        # tangent n k x^(n-1) = kt at x0 where k x0^n = F: x0 = n F / kt
        x0 = n * cond.force_n / kt
        return kt / (n * x0 ** (n - 1.0))

    def _step_hc(self, f: float) -> None:
        o, h = self.obj, self.h
        k, n, lam = self.hc_k(), o.exponent, o.hc_lambda_s_per_m
        x0 = float(self.x[0])
        if f <= 0.0:  # relaxes to its surface at once (no mass)
            x = max(0.0, min(x0, x0 - h * 0.5))
            x = 0.0 if x0 <= 0.0 else x
        else:
            x = max(x0, 1e-9)
            for _ in range(30):  # Newton on k x^n (1 + lam (x - x0)/h) = f
                xn = x**n
                g = k * xn * (1.0 + lam * (x - x0) / h) - f
                dg = k * n * x ** (n - 1.0) * (1.0 + lam * (x - x0) / h) + k * xn * lam / h
                step = g / dg
                x = max(x - step, 1e-12)
                if abs(step) < 1e-12:
                    break
        self.v[0] = (x - x0) / h
        self.x[0] = x

    def reported(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(K_o, K_o_eff, K_o_stiff, B_o) as the server reports them (server.world.World)."""
        k_o = 1.0 / np.diag(self.c_nom)
        k_eff = effective_stiffness(self.c_nom, k_o)
        k_stiff = stiff_stiffness(self.c_nom, k_o)
        b_o = self.obj.damping_n_s_per_m / self.h if self.obj.b_o_reported else 0.0
        return k_o, k_eff, k_stiff, b_o


@dataclass
class _User:
    session: ClientSession
    servo: ServoCore
    device: SimDevice
    target: Callable[[float], float]
    up: list[tuple[float, int, float, float]] = field(default_factory=list)  # (t, seq, f, depth)
    down: list[tuple[float, int, str]] = field(default_factory=list)  # (t, seq, frame)
    jobs: list[tuple[float, int, str, tuple[Any, ...]]] = field(default_factory=list)
    seq: int = 0
    latest: tuple[int, float, float] = (-1, 0.0, 0.0)  # (seq, force, probe depth) at the server
    busy_until: float = 0.0


def _min_jerk(t: float, t0: float, t1: float, a: float, b: float) -> float:
    if t <= t0:
        return a
    if t >= t1:
        return b
    s = (t - t0) / (t1 - t0)
    return a + (b - a) * (10 * s**3 - 15 * s**4 + 6 * s**5)


def user_target(
    depth_m: float, *, nudge: bool, press: tuple[float, float], release_s: float
) -> Callable[[float], float]:
    """The hand's aim [m, depth inward] over time: above the surface, a press to ``depth_m``,
    a 2 mm nudge out and back in 0.1 s (``nudge``), a hold, and a release."""
    start = -5e-3

    def y(t: float) -> float:
        d = _min_jerk(t, press[0], press[1], start, depth_m)
        if nudge and NUDGE_S <= t < NUDGE_S + 0.1:
            d -= 2e-3 * math.sin(math.pi * (t - NUDGE_S) / 0.1)
        if t >= release_s:
            d = _min_jerk(t, release_s, release_s + 0.3, depth_m, start - 5e-3)
        return d

    return y


def _welcome(name: str, sim_rate_hz: float) -> str:
    info = ObjectInfo(
        n_vertices=0,
        n_faces=0,
        center_m=(0.0, 0.0, -0.05),
        radius_m=0.05,
        bounds_min_m=(-0.05, -0.05, -0.1),
        bounds_max_m=(0.05, 0.05, 0.0),
        top_m=(0.0, 0.0, 0.0),
        top_normal=(0.0, 0.0, 1.0),
        side_m=(0.05, 0.0, -0.05),
        side_normal=(1.0, 0.0, 0.0),
    )
    return encode(
        Welcome(
            user_id=name,
            name=name,
            role="user",
            sim_rate_hz=sim_rate_hz,
            object=info,
            link=LinkConditions(),
        )
    )


@dataclass(frozen=True, slots=True)
class RunResult:
    """What a user of the box would notice in one run (SI-derived units as named)."""

    stable: bool
    hold_p2p_mm: float
    runaway: bool
    force_hold_n: float
    sources: dict[str, int]
    passivity_dissipated_mj: float


def run(
    cond: DrawnCondition,
    hand: DrawnHand,
    *,
    mode: Literal["p", "pi"] = "pi",
    phase: float = 0.0,
    passivity: Literal["auto", "on", "off"] = "auto",
    rng_seed: int = 0,
) -> RunResult:
    """One run of ``cond`` with ``hand`` holding user 0 (partners: the simulated default hand).

    ``phase`` in [0, 1): where in the simulation period the server's tick falls against the
    client's states (sent every half period): the sampling phase of Step 3.
    """
    rng = np.random.default_rng(rng_seed)
    prof = get_sim_profile(PROFILE)
    n_ratio = round(SERVO_HZ / cond.sim_rate_hz)
    cfg, lm = servo_setup(mode, cond.sim_rate_hz, passivity)
    table = _copy_table()
    obj = ObjectSim(cond)
    users: list[_User] = []
    k_true = cond.obj.k_ratio * cond.k_o
    for i in range(cond.users):
        if i == 0:
            hp = HandParams(
                stiffness_n_per_m=hand.stiffness_n_per_m,
                damping_n_s_per_m=max(hand.damping_n_s_per_m - prof.limits.damping_n_s_per_m, 0.0),
                mass_kg=max(hand.mass_kg - prof.mass_kg, 0.0),
            )
            depth = cond.force_n / k_true + cond.force_n / hand.stiffness_n_per_m
            target = user_target(depth, nudge=True, press=PRESS_S, release_s=RELEASE_S)
        else:
            hp = HandParams()
            f = 1.5 * cond.force_n
            depth = f / k_true + f / hp.stiffness_n_per_m
            target = user_target(
                depth, nudge=False, press=(PARTNER_S[0], PARTNER_S[0] + 0.4), release_s=PARTNER_S[1]
            )
        tgt = target

        def traj(t: float, tgt: Callable[[float], float] = tgt) -> tuple[float, float, float]:
            return (0.0, 0.0, -tgt(t))

        dev = SimDevice(prof, traj, hp, servo_period_s=T)
        dev.open()
        servo = ServoCore(dev, cfg, local_model=lm)
        session = ClientSession(
            f"u{i}",
            servo_rate_hz=SERVO_HZ,
            device=DeviceInfo(
                profile=PROFILE,
                max_force_n=prof.limits.max_force_n,
                max_stiffness_n_per_m=prof.limits.max_stiffness_n_per_m,
                max_damping_n_s_per_m=prof.limits.max_damping_n_s_per_m,
            ),
            mode=mode,
            b_h_max=prof.limits.max_damping_n_s_per_m,
            gain_table=table if i == 0 else _copy_table(),
        )
        session.hello(0.0)
        session.receive(_welcome(f"u{i}", cond.sim_rate_hz), 2.0 * cond.one_way_delay_s)
        servo.enable_forces()
        users.append(_User(session, servo, dev, target))

    def delay() -> float:
        return max(0.0, cond.one_way_delay_s + float(rng.uniform(-cond.jitter_s, cond.jitter_s)))

    n_steps = round(DURATION_S * SERVO_HZ)
    state_every = max(1, n_ratio // 2)
    tick_offset = int(phase * n_ratio) % n_ratio
    ping_every = 500
    sim_tick = 0
    probe = np.zeros(n_steps)
    force = np.zeros(n_steps)
    sources: dict[str, int] = {}
    for n in range(n_steps):
        t = n * T
        for ui, u in enumerate(users):
            s = u.session
            # frames that arrived
            while u.down and u.down[0][0] <= t:
                _, _, frame = heapq.heappop(u.down)
                upd = s.receive(frame, t)
                u.servo.notify_link(t)
                if upd is not None:
                    u.servo.set_patch(upd)
                    if ui == 0:
                        src = upd.choice.source if upd.choice is not None else "none"
                        sources[src] = sources.get(src, 0) + 1
            _run_jobs(u, t, ui)
            u.servo.tick(t)
            if n % ping_every == 0:
                frame = s.ping(t)
                pid = s._ping_id
                back = t + delay() + delay()
                heapq.heappush(
                    u.down, (back, -1, encode(Pong(id=pid, t_client_s=t, tick=sim_tick)))
                )
            if n % state_every == 0:
                snap = u.servo.latest()
                if snap is not None:
                    smp = ServoSample.from_snapshot(snap)
                    u.seq += 1
                    # the force the user pushes the object with: minus the force on the handle
                    u.up.append((t + delay(), u.seq, float(smp.force_n[2]), -float(smp.probe_m[2])))
        probe[n] = -users[0].device.position_m[2]
        snap0 = users[0].servo.latest()
        force[n] = float(snap0.force_n[2]) if snap0 is not None else 0.0
        if not math.isfinite(probe[n]) or abs(probe[n]) > RUNAWAY_M:
            return RunResult(False, math.inf, True, math.nan, sources, 0.0)
        if n % n_ratio == tick_offset:
            _server_tick(obj, users, sim_tick, delay, t)
            sim_tick += 1
    t_axis = np.arange(n_steps) * T
    w = (t_axis >= HOLD_WINDOW_S[0]) & (t_axis < HOLD_WINDOW_S[1])
    tw = t_axis[w]
    pw = probe[w]
    coef = np.polyfit(tw - tw.mean(), pw, 2)
    resid = pw - np.polyval(coef, tw - tw.mean())
    p2p = float(np.ptp(resid))
    pc = users[0].servo.safety.passivity
    return RunResult(
        stable=p2p < STABLE_P2P_M,
        hold_p2p_mm=p2p * 1e3,
        runaway=False,
        force_hold_n=float(np.mean(force[w])),
        sources=sources,
        passivity_dissipated_mj=(pc.dissipated_energy_j * 1e3) if pc is not None else 0.0,
    )


_TEMPLATE: list[GainTable] = []


def _copy_table() -> GainTable:
    """A fresh table holding the shipped designs, as a client starts with (no cache)."""
    if not _TEMPLATE:
        t = GainTable()
        preload(t, cache=False)
        _TEMPLATE.append(t)
    return copy.deepcopy(_TEMPLATE[0])


def _server_tick(
    obj: ObjectSim, users: list[_User], tick: int, delay: Callable[[], float], t: float
) -> None:
    """The server's tick: latest forces that arrived, step, a patch to each user."""
    m = len(users)
    f = np.zeros(m)
    for i, u in enumerate(users):
        arrived = [x for x in u.up if x[0] <= t]
        if arrived:
            newest = max(arrived, key=lambda x: x[1])
            if newest[1] > u.latest[0]:
                u.latest = (newest[1], newest[2], newest[3])
            u.up = [x for x in u.up if x[0] > t]
        seq, force, depth = u.latest
        pen = depth - float(obj.x[i])
        f[i] = max(force, 0.0) if pen > -1e-3 else 0.0
    obj.step(f)
    k_o, k_eff, k_stiff, b_o = obj.reported()
    alone = m == 1
    for i, u in enumerate(users):
        surf = float(obj.x[i])
        depth = u.latest[2]
        pen = depth - surf
        near = pen > -0.01
        ke = float(k_eff[i]) if (near and m > 1) else float(k_o[i])
        ks = float(k_stiff[i]) if (near and m > 1) else float(k_o[i])
        rest = PlaneModel(point=(0.0, 0.0, -obj.rest), normal=(0.0, 0.0, 1.0)) if alone else None
        msg = Patch(
            tick=tick,
            primitive=PlaneModel(point=(0.0, 0.0, -surf), normal=(0.0, 0.0, 1.0)),
            proxy_m=(0.0, 0.0, -surf),
            normal=(0.0, 0.0, 1.0),
            penetration_m=pen,
            in_contact=pen > 0.0,
            k_o=float(k_o[i]),
            k_o_eff=ke,
            k_o_stiff=ks,
            b_o=b_o,
            own_force_n=float(f[i]),
            rest_plane=rest,
        )
        heapq.heappush(u.down, (t + delay(), tick, encode(msg)))


def _run_jobs(u: _User, t: float, ui: int) -> None:
    """The link's workers: take the session's jobs, answer them after their latency."""
    s = u.session
    table = s.gain_table
    if s.design_wanted is not None:
        key, k_o = s.design_wanted
        s.design_wanted = None
        heapq.heappush(
            u.jobs,
            (t + JOB_LATENCY_S["design"], id(key) ^ int(k_o), "design", (key, table.cell(k_o))),
        )
    if s.interim_wanted is not None:
        key, cell, cands = s.interim_wanted
        s.interim_wanted = None
        heapq.heappush(u.jobs, (t + JOB_LATENCY_S["check"], cell, "check", (key, cell, cands)))
    while s.plane_wanted:
        key, cell, dcell = s.plane_wanted.pop()
        heapq.heappush(u.jobs, (t + JOB_LATENCY_S["plane"], cell, "plane", (key, cell, dcell)))
    delivered = False
    while u.jobs and u.jobs[0][0] <= t:
        _, _, kind, args = heapq.heappop(u.jobs)
        if kind == "design":
            key, cell = args
            d = _memo("design", design_cell, key, cell, table.grid_ratio, table.hand_box)
            if isinstance(d, GainDesign):
                table.store(key, cell, d)
        elif kind == "check":
            key, cell, cands = args
            d = _memo(
                "check",
                interim_design,
                key,
                cell,
                table.grid_ratio,
                table.hand_box,
                tuple(cands),
                True,
            )
            if isinstance(d, GainDesign):
                s.store_interim(key, cell, d)
            else:
                s.interim_failed(key, cell)
        else:
            key, cell, dcell = args
            design = None
            if dcell >= 0:
                from haptic_collab.shared.gains.choose import table_design

                design = table_design(table, key, table.grid_point(dcell) * 1.0001)[0]
            p = _memo("plane", verified_plane, key, cell, table.grid_ratio, table.hand_box, None)
            p = None if isinstance(p, ValueError) else plane_against(p, key, design)
            s.store_plane(key, cell, p, dcell)
        delivered = True
    if delivered:
        upd = s.retry_waiting(t)
        if upd is not None:
            u.servo.set_patch(upd)
