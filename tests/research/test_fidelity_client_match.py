"""The 1-D benchmark's local model is the client's: the vectorised simulator
(:func:`haptic_collab.research.fidelity_1d.simulate`) renders, tick for tick, the force the
product's own :class:`client.render.LocalRenderer` renders on the same object, network and gain
table, through every hand-over (transfer force, damper carry, each design's proxy hold, a
change of C_h sliding in with either hold), and the rest plane a user alone renders; on random
inputs (tables, objects, K_o, rates, delays, sampling phases, trajectories) with each patch's
gains chosen by the product's own policy, :func:`shared.gains.choose.choose`."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest

from haptic_collab.client.render import LocalRenderer
from haptic_collab.research.fidelity_1d import simulate
from haptic_collab.research.fidelity_cases import (
    PRESS,
    STIFFENING,
    TAP,
    Cell,
    ObjectModel,
    Trajectory,
    stale_ticks,
    stiffening_depth,
    stiffening_tangent,
)
from haptic_collab.research.fidelity_schemes import (
    PRODUCT_GAIN_TRANSFER_S,
    DeviceModel,
    Rendering,
    TableCell,
    TableGains,
    rendering_for,
)
from haptic_collab.shared.full_loop import ProxyHold
from haptic_collab.shared.gains.choose import Contact, Known, Options, choose
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.policy import DESIGN_MARGIN
from haptic_collab.shared.gains.rest_plane import rest_plane_gains
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.local_model import LocalModelParams, ThresholdParams
from haptic_collab.shared.local_model_update import LocalModelUpdate, SurfacePatch
from haptic_collab.shared.primitives import make_plane

SERVO_HZ = 1000.0
#: a tap deep enough to leave the object and come back, through cells whose C_h rises and falls
LEAVING = replace(TAP, name="leaving tap", sine_amplitude_m=14e-3, sine_hz=3.0)
FMAX = DeviceModel().max_force_n
DEVICE_K = DeviceModel().max_stiffness_n_per_m
DEVICE_B = DeviceModel().max_damping_n_s_per_m


class _Plane:
    """A 1-D surface at depth ``p`` [m] (depth positive inward, outward normal -x)."""

    def __init__(self, p: float) -> None:
        self.p = p

    def contact(self, x: float, y: float, z: float) -> tuple[float, float, float, float]:
        return x - self.p, -1.0, 0.0, 0.0


@dataclass
class _Patch:
    primitive: _Plane
    k_h: float
    i_gain: float
    b_h: float
    proxy_hold: str
    hold_ticks: int
    own_gain: float
    own_force_n: float
    recovery_m_per_n: float
    rest_plane: bool = False


def _client_forces(
    r: Rendering, k_o: float, rate: float, delay_ms: float, traj: Trajectory, obj: ObjectModel
) -> np.ndarray:
    """The force [N] per servo tick of the client's renderer, the probe a position source, on the
    simulator's object (implicit Euler, the stiffening object's tangent as its K_o) and network."""
    T = 1.0 / SERVO_HZ
    N = round(SERVO_HZ / rate)
    d = round(delay_ms * 1e-3 * SERVO_HZ)
    table = TableGains([r.table])
    k1 = k_o * obj.stiffness_error
    xs = obj.stiffening_m
    nonlin = obj.kind == "stiffening"
    assert obj.mass_kg == 0.0 and obj.relax_ratio == 0.0 and obj.damping_n_s_per_m == 0.0
    params = LocalModelParams(
        k_h=r.k_h,
        i_gain=r.i_gain,
        servo_period_s=T,
        threshold=ThresholdParams(mode="fixed", theta_m=r.theta_m),
        release_time_s=r.release_time_s,
        integral_limit_n=FMAX,
        gain_transfer_s=r.gain_transfer_s,
    )
    rd = LocalRenderer(params, own_force_limit_n=FMAX)
    L = d + 2
    up = np.zeros(L)
    down: list[tuple[float, float, float]] = [(0.0, k_o, 0.0)] * L
    down_seq = np.zeros(L, dtype=int)
    pub, pub_seq, seen, xo = (0.0, k_o, 0.0), 0, 0, 0.0
    n_steps = round(traj.duration_s * SERVO_HZ)
    y, _ = traj.target(np.arange(n_steps, dtype=np.float64) * T)
    out = np.empty(n_steps)
    x_prev = y[0]
    for n in range(n_steps):
        x = float(y[n])
        k = n - 1 - d
        if k >= 0 and down_seq[k % L] != seen:
            seen = int(down_seq[k % L])
            val, k_est, got = down[k % L]
            kg, ig, bg, og, fg = (float(a[0]) for a in table.gains_and_hold(np.array([k_est])))
            if r.rest_plane:  # alone, no verified plane: the rest plane at depth 0
                rest = rest_plane_gains(k_est, 0.0, rate, DEVICE_K, DEVICE_B, servo_period_s=T)
                kg, ig, bg, og, fg, val = rest.k_h, 0.0, rest.b_h, 0.0, False, 0.0
            hold = "foh" if fg else "zoh"
            rec = 1.0 / k_o if ig > 0.0 else 0.0
            patch = _Patch(_Plane(val), kg, ig, bg, hold, N, og, max(got, 0.0), rec, r.rest_plane)
            rd.hand_over(patch, False)  # type: ignore[arg-type]
        f = min(max(rd.render(x, 0.0, 0.0, x - x_prev, 0.0, 0.0)[0], -FMAX), FMAX)
        out[n] = f
        x_prev = x
        up[n % L] = f
        if n % N == 0:  # the simulation's tick: the force that arrived pushes the object
            got = float(up[(n - d) % L]) if n >= d else 0.0
            f_in = max(got, 0.0)
            xo = float(stiffening_depth(k1, xs, np.array(f_in))) if nonlin else f_in / k1
            k_est = float(stiffening_tangent(k_o, xs, np.array(max(xo, 0.0)))) if nonlin else k_o
            own = float(table.gains(np.array([k_est]))[3][0])
            pub, pub_seq = (xo - own * f_in, k_est, got), pub_seq + 1
        down[n % L] = pub
        down_seq[n % L] = pub_seq
    return out


def _mixed_table(seed: int) -> dict[int, GainDesign]:
    """Designed cells 40-74 with random gains: P and PI, dampers or none, C_h or none, and zero-
    or first-order holds, so a press through them hands over every kind of change."""
    g = GainTable()
    rng = np.random.default_rng(seed)
    cells = {}
    for c in range(40, 75):
        gp = g.grid_point(c)
        hold: ProxyHold = "foh" if rng.random() < 0.5 else "zoh"
        d = GainDesign(
            k_h=gp * rng.uniform(0.3, 1.0),
            i_gain=gp * rng.uniform(0.0, 10.0) * (rng.random() < 0.6),
            b_h=rng.uniform(0.0, 5.0) * (rng.random() < 0.7),
            proxy_hold=hold,
            worst_spectral_radius=0.9,
            rho_limit=0.95,
            felt_stiffness_ratio_1hz=1.0,
            felt_stiffness_ratio_8hz=1.0,
            k_o=gp,
            k_o_range=(0.85 * gp, 1.4 * gp),
            rate_ratio=20,
            delay_ticks=0,
            mode="pi",
            own_gain=rng.uniform(0.0, 1.0) / gp * (rng.random() < 0.8),
            scale_max=rng.uniform(1.0, 1.1),
        )
        cells[c] = d
    return cells


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize(
    ("traj", "rate", "delay_ms"), [(PRESS, 20.0, 0.0), (TAP, 50.0, 20.0), (LEAVING, 20.0, 0.0)]
)
def test_the_simulators_local_model_renders_what_the_client_renders(
    seed: int, traj: Trajectory, rate: float, delay_ms: float
) -> None:
    designs = _mixed_table(seed)
    g = GainTable()
    table = [TableCell.from_design(c, d, g.grid_ratio) for c, d in designs.items()]
    k_o = g.grid_point(44)
    # the product's rendering of the design for K_o (its cell's, unscaled at the grid point),
    # with another user near (no rest plane)
    # the renderer is compared here; the passivity layer the client adds at the device port is
    # compared with the product's controller in test_fidelity_1d.py
    r = replace(
        rendering_for(
            "local-p", sim_rate_hz=rate, design=designs[44], table=table, rest_plane=False
        ),
        passivity=False,
    )
    assert r.gain_transfer_s == PRODUCT_GAIN_TRANSFER_S > 0.0
    for rendering in (r, replace(r, gain_transfer_s=0.0)):
        sim = simulate([Cell(rendering, k_o, rate, delay_ms, None, traj, STIFFENING)]).f[0]
        client = _client_forces(rendering, k_o, rate, delay_ms, traj, STIFFENING)
        # the press went through several cells: the K_o reported at its deepest is cells above
        deepest = stiffening_depth(k_o, STIFFENING.stiffening_m, np.array(sim.max()))
        k_top = float(stiffening_tangent(k_o, STIFFENING.stiffening_m, deepest))
        assert GainTable().cell(k_top) - GainTable().cell(k_o) >= 3
        np.testing.assert_allclose(sim, client, rtol=0.0, atol=1e-9)


@pytest.mark.parametrize(("traj", "rate", "delay_ms"), [(PRESS, 20.0, 0.0), (LEAVING, 50.0, 20.0)])
def test_alone_the_simulator_renders_the_rest_plane_as_the_client(
    traj: Trajectory, rate: float, delay_ms: float
) -> None:
    # a press into the stiffening object, the user alone: the rest plane with the tangent K_o
    # reported in every patch, as the client renders it; no design's surface, no compensation
    designs = _mixed_table(1)
    g = GainTable()
    table = [TableCell.from_design(c, d, g.grid_ratio) for c, d in designs.items()]
    k_o = g.grid_point(44)
    r = replace(
        rendering_for("local-p", sim_rate_hz=rate, design=designs[44], table=table),
        passivity=False,  # the renderer alone (the passivity layer: test_fidelity_1d.py)
    )
    assert r.rest_plane
    sim = simulate([Cell(r, k_o, rate, delay_ms, None, traj, STIFFENING)]).f[0]
    client = _client_forces(r, k_o, rate, delay_ms, traj, STIFFENING)
    np.testing.assert_allclose(sim, client, rtol=0.0, atol=1e-9)
    # and it is not the design's rendering
    other = simulate(
        [Cell(replace(r, rest_plane=False), k_o, rate, delay_ms, None, traj, STIFFENING)]
    )
    assert np.max(np.abs(other.f[0] - sim)) > 0.05


def _chosen_client_forces(
    r: Rendering,
    key: GainKey,
    table: GainTable,
    k_o: float,
    rate: float,
    delay_ms: float,
    traj: Trajectory,
    obj: ObjectModel,
    lag: int,
    sources: set[str],
) -> np.ndarray:
    """The force [N] per servo tick of the product's client on the simulator's object and
    network, the probe a position source: each patch's gains from the product's gain policy
    (:func:`shared.gains.choose.choose`, nothing verified but the table's designs, no planes),
    rendered by :class:`client.render.LocalRenderer`; the simulation reads what the servo sent
    ``lag`` servo ticks before its freshest. The sources chosen are added to ``sources``."""
    T = 1.0 / SERVO_HZ
    N = round(SERVO_HZ / rate)
    d = round(delay_ms * 1e-3 * SERVO_HZ)
    k1 = k_o * obj.stiffness_error
    xs = obj.stiffening_m
    nonlin = obj.kind == "stiffening"
    assert obj.mass_kg == 0.0 and obj.relax_ratio == 0.0 and obj.damping_n_s_per_m == 0.0
    options = Options(
        servo_rate_hz=SERVO_HZ, sim_rate_hz=rate, k_h_max=DEVICE_K, b_h_max=DEVICE_B,
        mode="p", gains="local", rest_plane=r.rest_plane,
    )  # fmt: skip
    known = Known(table=table, interim={}, planes={})
    params = LocalModelParams(
        k_h=r.k_h,
        i_gain=r.i_gain,
        servo_period_s=T,
        threshold=ThresholdParams(mode="fixed", theta_m=r.theta_m),
        release_time_s=r.release_time_s,
        integral_limit_n=FMAX,
        gain_transfer_s=r.gain_transfer_s,
    )
    rd = LocalRenderer(params, own_force_limit_n=FMAX)
    L = d + lag + 2
    up = np.zeros(L)
    down: list[tuple[float, float, float]] = [(0.0, k_o, 0.0)] * L
    down_seq = np.zeros(L, dtype=int)
    pub, pub_seq, seen = (0.0, k_o, 0.0), 0, 0
    n_steps = round(traj.duration_s * SERVO_HZ)
    y, _ = traj.target(np.arange(n_steps, dtype=np.float64) * T)
    out = np.empty(n_steps)
    x_prev = y[0]
    normal = (-1.0, 0.0, 0.0)
    in_use: LocalModelUpdate | None = None  # the update rendering (the session's last_update)
    for n in range(n_steps):
        x = float(y[n])
        k = n - 1 - d
        if k >= 0 and down_seq[k % L] != seen:
            seen = int(down_seq[k % L])
            surface_m, k_est, got = down[k % L]
            f_s = max(got, 0.0)
            patch_in = SurfacePatch(
                tick=seen, primitive=make_plane((surface_m, 0.0, 0.0), normal),
                proxy=(surface_m, 0.0, 0.0), normal=normal, penetration_m=0.0,
                in_contact=f_s > 0.0, k_o=k_est, k_o_eff=k_est, k_o_stiff=k_est, b_o=0.0,
                own_force_n=f_s,
                rest_plane=make_plane((0.0, 0.0, 0.0), normal) if r.rest_plane else None,
            )  # fmt: skip
            choice = choose(patch_in, None, Contact(key=key, in_use=in_use), known, options)
            assert choice.source is not None
            sources.add(choice.source)
            if choice.source == "rest":
                assert choice.rest is not None
                kg, ig, bg, og, hold, p = choice.rest.k_h, 0.0, choice.rest.b_h, 0.0, "zoh", 0.0
            else:
                g = choice.gains
                assert g is not None
                kg, ig, bg, og, hold = g.k_h, g.i_gain, g.b_h, g.own_gain, g.proxy_hold
                p = surface_m - og * f_s  # the surface moved out by C_h F_s (from_wire)
            rec = 1.0 / k_o if ig > 0.0 else 0.0
            rest_on = choice.source == "rest"
            patch = _Patch(_Plane(p), kg, ig, bg, hold, N, og, f_s, rec, rest_on)
            in_use = LocalModelUpdate(
                primitive=make_plane((p, 0.0, 0.0), normal), k_h=kg, i_gain=ig, b_h=bg,
                proxy_hold=hold, hold_ticks=N, own_gain=og, surface=patch_in, rest_plane=rest_on,
            )  # fmt: skip
            rd.hand_over(patch, False)  # type: ignore[arg-type]
        f = min(max(rd.render(x, 0.0, 0.0, x - x_prev, 0.0, 0.0)[0], -FMAX), FMAX)
        out[n] = f
        x_prev = x
        up[n % L] = f
        if n % N == 0:  # the simulation's tick: the force that arrived pushes the object
            at = n - d - lag
            got = float(up[at % L]) if at >= 0 else 0.0
            f_in = max(got, 0.0)
            xo = float(stiffening_depth(k1, xs, np.array(f_in))) if nonlin else f_in / k1
            k_est = float(stiffening_tangent(k_o, xs, np.array(max(xo, 0.0)))) if nonlin else k_o
            pub, pub_seq = (xo, k_est, got), pub_seq + 1
        down[n % L] = pub
        down_seq[n % L] = pub_seq
    return out


def test_the_simulator_renders_the_products_policy_on_random_inputs() -> None:
    # random gain tables (cells missing below and above, so the policy falls back both ways),
    # objects, K_o, rates, delays, sampling phases, presses and taps, alone or not: the
    # simulator's vectorised servo law and gain choice give, tick for tick, the force of the
    # product's policy (shared.gains.choose.choose) rendered by the client's LocalRenderer
    rng = np.random.default_rng(20261127)
    g = GainTable()
    sources: set[str] = set()
    worst = 0.0
    for case in range(10):
        rate = float(rng.choice([10.0, 20.0, 50.0, 100.0]))
        delay_ms = float(rng.integers(0, 61))
        designs = _mixed_table(int(rng.integers(0, 1000)))
        # the cell of the K_o at rest designed, as the benchmark designs the grid's K_o (a first
        # contact in a cell not designed waits with forces off: the product's rule)
        c0 = int(rng.integers(40, 75))
        drawn = rng.choice(sorted(designs), size=int(rng.integers(3, 15)), replace=False)
        cells = sorted({c0, *(int(c) for c in drawn)})
        k_o = g.grid_point(c0) * float(rng.uniform(1.0, g.grid_ratio))
        if rng.random() < 0.5:
            obj = ObjectModel("spring-r", stiffness_error=float(rng.uniform(0.8, 1.25)))
        else:
            obj = ObjectModel("stiff-r", "stiffening", stiffening_m=float(rng.uniform(5e-3, 2e-2)))
        depth = float(rng.uniform(2e-3, 10e-3))
        traj = Trajectory(
            f"random-{case}", duration_s=2.5, y0_m=-2e-3, y1_m=depth, ramp_start_s=0.1,
            ramp_s=float(rng.uniform(0.2, 0.6)), sine_amplitude_m=float(rng.uniform(0.5e-3, 6e-3)),
            sine_hz=float(rng.uniform(1.0, 5.0)), sine_start_s=1.0, sine_end_s=2.5,
            hold_window_s=(2.0, 2.5), energy_window_s=(0.0, 2.5),
        )  # fmt: skip
        key = GainKey(
            servo_rate_hz=SERVO_HZ, sim_rate_hz=rate, delay_ticks=0, mode="p",
            margin=DESIGN_MARGIN, k_h_max=DEVICE_K, b_h_max=DEVICE_B,
        )  # fmt: skip
        table = GainTable()
        for c in cells:
            table.store(key, int(c), designs[int(c)])
        tcells = [TableCell.from_design(int(c), designs[int(c)], g.grid_ratio) for c in cells]
        first = table.lookup(key, k_o) or table.fallback(key, k_o)
        assert first is not None
        alone = bool(rng.random() < 0.4)
        r = replace(
            rendering_for(
                "local-p", sim_rate_hz=rate, design=first, table=tcells, rest_plane=alone
            ),
            passivity=False,  # the renderer alone (the passivity layer: test_fidelity_1d.py)
        )
        stale = bool(rng.random() < 0.5)
        lag = stale_ticks(round(SERVO_HZ / rate)) if stale else 0
        sim = simulate([Cell(r, k_o, rate, delay_ms, None, traj, obj, stale_sample=stale)]).f[0]
        client = _chosen_client_forces(r, key, table, k_o, rate, delay_ms, traj, obj, lag, sources)
        assert np.max(np.abs(client)) > 0.3  # the press is felt
        worst = max(worst, float(np.max(np.abs(sim - client))))
        np.testing.assert_allclose(sim, client, rtol=0.0, atol=1e-9, err_msg=f"case {case}")
    # the draws reached every source the simulator renders without planes
    assert {"design", "near", "rest"} <= sources, sources
    assert worst <= 1e-9
