"""The fidelity benchmark's two-user 3-D cells: B rests on the object's side while A presses its
top, and what B feels of A's press.

The one-user cells' blocks (:mod:`haptic_collab.research.fidelity_users_3d`: servo, simulated
Phantom Desktop, default hand, the same delay both ways) twice on one World, the demo's scene,
run by the harness of :mod:`haptic_collab.research.harness_3d`. What B feels of A's press is
compared with what a probe held still there would feel (:class:`Pair3D`). Only the schemes whose
servo renders a patch run here (:data:`PAIR_SCHEMES`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from haptic_collab.client.devices.sim import HandParams
from haptic_collab.research.fidelity_cases import PRESS, Trajectory
from haptic_collab.research.fidelity_schemes import DeviceModel
from haptic_collab.research.fidelity_users_3d import (
    DEFAULT_DEVICE,
    check_delay,
    check_known,
    check_runs,
    executor,
    rendering_3d,
    renewed_patch,
    scheme_device,
    scheme_servo,
)
from haptic_collab.research.harness_3d import (
    RATE_RATIO,
    SERVO_RATE_HZ,
    ServoPort,
    Timing,
    reused_world,
    run_multirate,
)
from haptic_collab.server.object_info import object_info
from haptic_collab.server.world import ContactInput, World
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.primitives import moved_out
from haptic_collab.shared.types import FloatArray

#: The schemes of the two-user cells: those whose servo renders a patch the World renews (the
#: direct schemes hold the World's force, which is already the object's, coupling included).
PAIR_SCHEMES: tuple[str, ...] = ("local-p", "local-pi", "mmt", "static-local")
#: Length [s] of a two-user cell.
PAIR_DURATION_S = 8.0
#: B's intention: from 2 mm outside the side of the object to 3 mm in, from 0.1 s over 0.4 s,
#: then rest there (the demo's resting user).
PAIR_REST = Trajectory(
    "rest",
    duration_s=PAIR_DURATION_S,
    y0_m=-2e-3,
    y1_m=3e-3,
    ramp_start_s=0.1,
    ramp_s=0.4,
    hold_window_s=(7.0, 8.0),
    energy_window_s=(0.0, PAIR_DURATION_S),
)
#: A's intention: :data:`haptic_collab.research.fidelity_cases.PRESS` (10 mm into the top) started at 3 s, held to 8 s.
PAIR_PRESS = replace(
    PRESS,
    duration_s=PAIR_DURATION_S,
    ramp_start_s=3.0,
    hold_window_s=(7.0, 8.0),
    energy_window_s=(0.0, PAIR_DURATION_S),
)
#: Where B rests before A touches, and where A holds [s].
PAIR_REST_WINDOW_S = (2.0, 3.0)
PAIR_HOLD_WINDOW_S = (7.0, 8.0)
#: A hold whose probe moves more than this peak to peak [m] in its window is not settled.
PAIR_SETTLED_P2P_M = 0.5e-3
#: B feels A when its force rises by at least this share of ``object_force_rise_n``. B's hand
#: yields, so even the object itself is felt as about half of that rise (0.106 of 0.202 N on the
#: balloon through the product's local model); a surface that does not move gives none.
PAIR_FEELS_SHARE = 0.25


@dataclass(frozen=True)
class Pair3D:
    """One two-user cell: B rests on the side of the object while A presses its top.

    Attributes
    ----------
    scheme, mesh : str
    stiffness_scale, delay_ms : float
    k_o_a, k_o_b : float
        K_o [N/m] the World reports at A's and B's rest contacts.
    b_force_rise_n : float
        B's force along its outward normal while A holds, less while B rests before A touches
        (means over :data:`PAIR_HOLD_WINDOW_S` and :data:`PAIR_REST_WINDOW_S`) [N]: what B feels
        of A's press.
    b_surface_out_mm : float
        How far the World's surface under B's rest point moves outward over the same windows
        (B's own dent included) [mm].
    object_force_rise_n : float
        ``k_o_b`` times the outward motion of the surface under B that is not B's own dent (the
        World's patch moved out by B's own force over K_o): the rise a probe held still there
        would feel [N].
    a_hold_p2p_mm, b_hold_p2p_mm : float
        Peak-to-peak probe depth in the hold window [mm].
    runaway : bool
        A probe reached the workspace end stop or went non-finite.
    settled : bool
        No runaway and both holds within :data:`PAIR_SETTLED_P2P_M`.
    b_feels_a : bool
        ``b_force_rise_n`` is at least :data:`PAIR_FEELS_SHARE` of ``object_force_rise_n``.
    """

    scheme: str
    mesh: str
    stiffness_scale: float
    delay_ms: float
    k_o_a: float
    k_o_b: float
    b_force_rise_n: float
    b_surface_out_mm: float
    object_force_rise_n: float
    a_hold_p2p_mm: float
    b_hold_p2p_mm: float
    runaway: bool
    settled: bool
    b_feels_a: bool

    def to_json(self) -> dict[str, Any]:
        """The cell object of ``haptic bench fidelity --json`` (``pairs_3d``)."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def side_point(world: World) -> FloatArray:
    """B's rest point (3,) [m]: of the rest surface's vertices within 1 mm of its smallest x, the
    one nearest the middle of the bounding box in y and z (the balloon's side at mid-height,
    where the demo's resting user is; the middle of a box's -x face, not an edge)."""
    v = np.asarray(world.vertices, dtype=np.float64)
    side = v[v[:, 0] <= v[:, 0].min() + 1e-3]
    mid = 0.5 * (v.min(axis=0) + v.max(axis=0))
    return np.asarray(side[int(np.argmin(np.hypot(*(side[:, 1:] - mid[1:]).T)))], np.float64)


def _recorder(
    dev: Any, point: FloatArray, nrm: FloatArray, x: FloatArray, f: FloatArray, hit: list[bool]
) -> Any:
    """After each servo tick: the probe depth read and the force written along ``nrm`` into
    ``x[n]``, ``f[n]``; ``hit[0]`` once the probe reaches the workspace end stop."""

    def record(n: int) -> None:
        q = np.asarray(dev.last_read, dtype=np.float64)
        x[n] = float(np.dot(point - q, nrm))
        f[n] = float(np.dot(np.asarray(dev.applied_force_n), nrm))
        hit[0] = hit[0] or dev.at_end_stop()

    return record


def run_3d_pair(
    scheme: str,
    *,
    stiffness_scale: float = 1.0,
    mesh: str = "balloon",
    delay_ms: float = 0.0,
    device: DeviceModel = DEFAULT_DEVICE,
    gain_table: GainTable | None = None,
) -> Pair3D:
    """Two users of one scheme on the World: B rests on the side while A presses the top.

    Both users are the one-user cell's (:func:`run_3d_cell`: servo, simulated Phantom Desktop,
    default hand, the same delay both ways), each with the scheme's rendering for the K_o at its
    own rest contact. B follows :data:`PAIR_REST`, A :data:`PAIR_PRESS`; the World ticks with
    both users' latest state. Whether B feels A is ``b_force_rise_n`` against
    ``object_force_rise_n``.

    Raises
    ------
    ValueError
        A scheme not in :data:`PAIR_SCHEMES`, a bad scale or delay.
    """
    check_known((scheme,), PAIR_SCHEMES, "two-user scheme")
    d = check_delay(delay_ms)
    T = 1.0 / SERVO_RATE_HZ
    world = reused_world(stiffness_scale, mesh)
    info = object_info(world.vertices, world.faces)
    points = {"a": np.array(info.top_m, dtype=np.float64), "b": side_point(world)}
    out0 = world.tick({u: ContactInput(probe=p, force=np.zeros(3)) for u, p in points.items()})
    trs = {"a": PAIR_PRESS, "b": PAIR_REST}
    n_ticks = round(PAIR_DURATION_S * SERVO_RATE_HZ)
    x = {u: np.empty(n_ticks) for u in points}
    f = {u: np.empty(n_ticks) for u in points}
    hit = [False]
    renderings = {}
    users = {}
    for u in ("a", "b"):
        nrm = np.asarray(out0[u].normal, dtype=np.float64)
        nrm = nrm / float(np.linalg.norm(nrm))
        k_o = float(out0[u].k_o)
        r = rendering_3d(scheme, k_o, delay_ms, device=device, gain_table=gain_table)
        dev = scheme_device(r, points[u], nrm, trs[u], device, HandParams())
        core, kw = scheme_servo(r, dev, device, k_o, out0[u])
        renderings[u] = r
        users[u] = ServoPort(
            core, dev.trajectory(0.0), r.i_gain, kw, _recorder(dev, points[u], nrm, x[u], f[u], hit)
        )
    surf_t: list[float] = []
    surf_b: list[float] = []
    rest_b: list[float] = []
    bx, by, bz = (float(c) for c in points["b"])

    def world_tick(n: int, states: dict[str, ContactInput]) -> dict[str, Any]:
        # the World's tick after servo tick n - 1, with both users' latest state
        out = world.tick(states)
        ob = out["b"]
        surf_t.append((n - 1) * T)
        surf_b.append(ob.primitive.contact(bx, by, bz)[0])
        rest = moved_out(ob.primitive, ob.own_force_n / float(ob.k_o))
        rest_b.append(rest.contact(bx, by, bz)[0])
        return {u: renewed_patch(renderings[u], out[u], out0[u]) for u in users}

    run_multirate(n_ticks, users, world_tick, Timing.network(d, RATE_RATIO))
    t = np.arange(n_ticks, dtype=np.float64) * T
    rw = (t >= PAIR_REST_WINDOW_S[0]) & (t < PAIR_REST_WINDOW_S[1])
    hw = (t >= PAIR_HOLD_WINDOW_S[0]) & (t < PAIR_HOLD_WINDOW_S[1])
    ts = np.asarray(surf_t)
    srw = (ts >= PAIR_REST_WINDOW_S[0]) & (ts < PAIR_REST_WINDOW_S[1])
    shw = (ts >= PAIR_HOLD_WINDOW_S[0]) & (ts < PAIR_HOLD_WINDOW_S[1])
    sb, rb = np.asarray(surf_b), np.asarray(rest_b)
    finite = all(np.isfinite(v).all() for v in (*x.values(), *f.values()))
    runaway = bool(hit[0] or not finite)
    p2p = {u: float(np.ptp(x[u][hw])) if finite else math.inf for u in users}
    k_o_b = float(out0["b"].k_o)
    rise = float(np.mean(f["b"][hw]) - np.mean(f["b"][rw]))
    object_rise = k_o_b * float(np.mean(rb[shw]) - np.mean(rb[srw]))
    return Pair3D(
        scheme=scheme,
        mesh=mesh,
        stiffness_scale=float(stiffness_scale),
        delay_ms=float(delay_ms),
        k_o_a=float(out0["a"].k_o),
        k_o_b=k_o_b,
        b_force_rise_n=rise,
        b_surface_out_mm=float(np.mean(sb[shw]) - np.mean(sb[srw])) * 1e3,
        object_force_rise_n=object_rise,
        a_hold_p2p_mm=p2p["a"] * 1e3,
        b_hold_p2p_mm=p2p["b"] * 1e3,
        runaway=runaway,
        settled=not runaway and max(p2p.values()) <= PAIR_SETTLED_P2P_M,
        b_feels_a=bool(rise >= PAIR_FEELS_SHARE * object_rise and object_rise > 0.0),
    )


def run_3d_pairs(
    schemes: Sequence[str] = PAIR_SCHEMES,
    *,
    stiffness_scales: Sequence[float] = (1.0,),
    delays_ms: Sequence[float] = (0.0, 100.0),
    meshes: Sequence[str] = ("balloon", "fem:box"),
    device: DeviceModel = DEFAULT_DEVICE,
    workers: int | None = 1,
    pool: Executor | None = None,
) -> list[dict[str, Any]]:
    """Every two-user cell (:func:`run_3d_pair`) of ``schemes`` x mesh x scale x delay: the
    balloon and the box as a FEM solid by default.

    ``workers`` and ``pool`` as :func:`haptic_collab.research.fidelity_3d.run_3d_cells` (each
    cell designs its own two renderings). Returns each cell's :meth:`Pair3D.to_json`, in the
    order scheme, mesh, scale, delay.

    Raises
    ------
    ValueError
        A scheme not in :data:`PAIR_SCHEMES`, a bad delay, or ``workers < 1``.
    """
    check_known(schemes, PAIR_SCHEMES, "two-user scheme")
    check_runs(delays_ms, workers)
    combos = [
        (s, m, sc, dm)
        for s in schemes
        for m in meshes
        for sc in stiffness_scales
        for dm in delays_ms
    ]
    if workers == 1 and pool is None:
        return [_pair_job(*c, device) for c in combos]
    with executor(pool, workers) as ex:
        futs = [ex.submit(_pair_job, *c, device) for c in combos]
        return [fu.result() for fu in futs]


def _pair_job(
    scheme: str, mesh: str, scale: float, delay_ms: float, device: DeviceModel
) -> dict[str, Any]:
    """One two-user cell's JSON (a worker's job)."""
    return run_3d_pair(
        scheme, mesh=mesh, stiffness_scale=scale, delay_ms=delay_ms, device=device
    ).to_json()
