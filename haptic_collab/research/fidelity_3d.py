"""The fidelity benchmark's schemes on the 3-D World: the product's own object, servo and hand.

``haptic bench fidelity``: the 1-D multirate simulator of :mod:`haptic_collab.research.fidelity_1d` carries
the full grid; the same schemes also run here on the server's :class:`server.world.World`
(the default water balloon, ``--stiffness-scale``, 20 Hz) without the network, one user pressing
the top with the default simulated hand. Every block is the product's code run in-process, tick
by tick, with integer ticks and no clock, socket or thread, on the harness of
:mod:`haptic_collab.research.harness_3d` (as :mod:`haptic_collab.research.reproduce_3d`); each
scheme's user is built by :mod:`haptic_collab.research.fidelity_users_3d`:

object
    :func:`server.main.build_world` with ``ServerOptions(sim_rate_hz=20,
    stiffness_scale=s)``, stepped once every N = 50 servo ticks. K_o is what the World reports
    at the top for a probe resting on it with no force (the first World tick of a run:
    :func:`top_contact`); that tick's :class:`shared.local_model_update.SurfacePatch` is also the patch the
    user holds before the run starts (the 1-D servo likewise knows the rest surface at t = 0).
user
    :class:`client.devices.sim.SimDevice`, profile ``phantom-desktop`` with the
    :class:`haptic_collab.research.fidelity_schemes.DeviceModel`'s force, stiffness and damping limits, default
    :class:`client.devices.sim.HandParams`; the hand target moves along the top's inward normal
    exactly as the 1-D trajectory ``y(t)``
    (:class:`haptic_collab.research.fidelity_users_3d.NormalTrajectory`); for ``impact`` the handle
    starts with the hand's velocity, as in the 1-D model. The probe hitting the device's
    workspace end stop counts as a runaway (the 1-D model's :data:`haptic_collab.research.fidelity_cases.RUNAWAY_M`
    cannot be reached inside the 120 mm workspace).
network
    one-way delay ``d`` whole servo ticks both ways, as the 1-D model: the World ticking at servo
    tick ``n`` (``n % N == 0``) uses the user's state published by the servo at tick ``n - d``
    (the client is modelled as sending its latest state every tick; the product's client sends
    it every half simulation period), and its output reaches the servo from tick ``n + 1 + d``.
    Before tick ``d`` the World sees the user's starting probe and no force.

Schemes (:func:`haptic_collab.research.fidelity_schemes.rendering_for` for the gains):

``local-p``, ``local-pi``, ``mmt``, ``static-local`` (:data:`SCHEMES_3D`)
    :class:`client.servo.ServoCore` at 1 kHz rendering the World's patch with the scheme's
    K_h, I, B_h, proxy hold (``hold_ticks = N``) and own-force compensation (the patch moved out by
    C_h times the World's ``own_force_n``, as the client's
    :meth:`shared.local_model_update.SurfacePatch.from_wire`); the World receives the probe and the force
    the servo rendered (Step 3 of the paper's section 6). The local models' gains are the
    product's design for the K_o at the top and the delay ticks the client would measure
    (:class:`shared.gains.table.GainTable`, margin 0.15, K_h <= the device's maximum stiffness,
    B_h <= its maximum damping); eq. 17 threshold fixed at 1 mm, release over two simulation
    periods, integral limited to the device's maximum force; passivity layer on
    (``ServoConfig(passivity=True)``, 1 mJ bias). Two safety features of the servo that the 1-D
    model does not have are set out of the way so that the schemes are compared as control laws:
    the force ramp at start-up is one tick (``ramp_s = T``) and the velocity limit is raised to
    :data:`haptic_collab.research.fidelity_users_3d.VELOCITY_LIMIT_M_S`; the device's stiffness
    limit is raised to K_h when K_h is above it
    (as :mod:`haptic_collab.research.reproduce_3d` does). ``mmt`` renders each patch moved out by the World's
    own-force deformation ``F / K_o`` (the rest surface it estimates) with that tick's K_o
    (capped at the device's stiffness) and its damper; ``static-local`` keeps the first patch (the
    rest surface) with the K_o at the top. The virtual coupling's tool and the force-jacobian
    need a simulation side the World does not have: they run in 1-D only.
``direct``, ``direct-tdpa``
    the World computes the contact force from the probe it received, applies it to the object
    as the user's contact force and sends it back; the user's loop (written here: read the
    device, write the force) holds it (zero-order hold) until the next one. The rule (see
    :data:`DIRECT_REFERENCE`): with ``(prim, K_o)`` the World's last :class:`SurfacePatch` for
    the user (the surface its last load produced), ``e`` the received probe's penetration below
    ``prim`` and ``F_prev >= 0`` the force the World applied last tick, the new force is

    - ``"undisturbed"`` (default): ``F = clamp(F_prev + K_o e, 0, F_max)``: ``K_o`` times the
      probe's depth below the surface as it would be without this user's own last push (the
      patch moved out by ``F_prev / K_o``, exact for the quasi-static balloon at a fixed
      contact). On a static probe it settles at ``F = K_o x``, the 1-D ``direct``;
    - ``"patch"``: ``F = clamp(K_o e, 0, F_max)``: the probe's depth below the deformed patch
      itself. The object then pushes back on its own deformation: a held probe gives ``F_k = K_o
      x - F_(k-1)``, a period-2 oscillation at the margin of eq. 8 (K_h = K_o) even without delay.

    The force acts along ``prim``'s outward normal at the probe. ``direct-tdpa`` passes the held
    force through :class:`shared.passivity.PassivityController` (alpha_max = the device's maximum
    damping, no energy bias, force limit the device's) at 1 kHz with the device velocity (backward
    difference of the positions read), as Ryu, Kwon and Hannaford 2004 (uncapped: the damping
    limit is :data:`UNCAPPED_DAMPING_N_S_PER_M`, the force clamp acts first).

Every force is clamped to the device's maximum (the servo's clamp, the World's rule above, the
PC's limit, and :meth:`SimDevice.write`).

Metrics (:func:`haptic_collab.research.fidelity_metrics.cell_metrics`) are taken on ``x`` = the probe position read by
the servo, as depth below the rest top along the inward normal [m], and ``f`` = the force written
to the device along the top's outward normal [N] (positive pushing the probe out), on the servo
clock ``t = n T`` with the windows of the matching :data:`haptic_collab.research.fidelity_cases.PRESS` /
:data:`haptic_collab.research.fidelity_cases.IMPACT`.

Two users (:func:`run_3d_pairs` of :mod:`haptic_collab.research.fidelity_pairs_3d`, where the
names of this paragraph live): the same blocks twice on one World, the demo's scene. B rests
on the balloon's side (:data:`PAIR_REST`) while A presses its top from 3 s (:data:`PAIR_PRESS`);
what B feels of A's press is compared with what a probe held still there would feel
(:class:`Pair3D`). Only the schemes whose servo renders a patch run there (:data:`PAIR_SCHEMES`).

Usage::

    from haptic_collab.research.fidelity_3d import run_3d_cells
    cells = run_3d_cells(("local-p", "direct"), stiffness_scales=(3.3,), delays_ms=(100.0,))
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np

from haptic_collab.client.devices.sim import HandParams
from haptic_collab.research.fidelity_cases import RUNAWAY_M, Cell, Run
from haptic_collab.research.fidelity_metrics import CellMetrics, cell_metrics
from haptic_collab.research.fidelity_schemes import DeviceModel, Rendering
from haptic_collab.research.fidelity_users_3d import (
    DEFAULT_DEVICE,
    DIRECT_REFERENCE,
    SCHEMES_3D,
    TRAJECTORIES_3D,
    UNCAPPED_DAMPING_N_S_PER_M,
    USER,
    DirectPort,
    DirectReference,
    PortDevice,
    check_delay,
    check_known,
    check_runs,
    executor,
    rendering_3d,
    renewed_patch,
    scheme_device,
    scheme_servo,
    top_contact,
    top_k_o,
)
from haptic_collab.research.harness_3d import (
    PROFILE,
    RATE_RATIO,
    SERVO_RATE_HZ,
    SIM_RATE_HZ,
    ServoPort,
    Timing,
    combined_hand,
    reused_world,
    run_multirate,
)
from haptic_collab.server.world import ContactInput
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.passivity import PassivityController, PassivityParams
from haptic_collab.shared.types import FloatArray

__all__ = ["Run3D", "run_3d_cell", "run_3d_cells"]


@dataclass
class Run3D:
    """One 3-D cell's time response and metrics.

    Attributes
    ----------
    cell : Cell
        The 1-D description of the cell (rendering, K_o, rate, delay, combined hand, trajectory)
        whose windows the metrics use.
    stiffness_scale : float
    mesh : str
        The object's ``--mesh`` (``balloon`` or a stress shape's name; ``fem:NAME`` for the FEM
        solid of that surface, :data:`haptic_collab.research.harness_3d.FEM_PREFIX`).
    t : (n,) float
        Servo tick times [s].
    x : (n,) float
        Probe depth [m] below the rest top along the inward normal, as read by the servo.
    f : (n,) float
        Force [N] written to the device along the top's outward normal (pushing the probe out).
    runaway : bool
        The probe reached the workspace end stop, left :data:`haptic_collab.research.fidelity_cases.RUNAWAY_M` or went
        non-finite.
    metrics : CellMetrics
    world_k_o : (m,) float
        K_o [N/m] the World reported at each of its ticks.
    """

    cell: Cell
    stiffness_scale: float
    mesh: str
    t: FloatArray
    x: FloatArray
    f: FloatArray
    runaway: bool
    metrics: CellMetrics
    world_k_o: FloatArray

    def to_json(self) -> dict[str, Any]:
        """The cell object of ``haptic bench fidelity --json`` (the 1-D cells' shape, ``model``
        ``"3d"``, plus ``stiffness_scale``; felt stiffness is measured in 1-D only: None)."""
        c = self.cell
        assert c.hand is not None
        return {
            "scheme": c.rendering.scheme,
            "model": "3d",
            "k_o_n_per_m": c.k_o,
            "sim_rate_hz": c.sim_rate_hz,
            "delay_ms": c.delay_ms,
            "hand": c.hand.as_dict(),
            "trajectory": c.trajectory.name,
            "stiffness_scale": self.stiffness_scale,
            "mesh": self.mesh,
            **self.metrics.to_json(),
            "felt_stiffness_ratio_1hz": None,
            "felt_stiffness_ratio_8hz": None,
        }


class _Trace:
    """After each servo tick of a one-user cell: the probe depth ``x[n]`` read by the servo below
    the rest top along the inward normal [m], the force ``f[n]`` written along the outward normal
    [N], and ``hit`` once the probe reaches the device's workspace end stop."""

    __slots__ = ("dev", "x", "f", "hit", "nx", "ny", "nz", "tx", "ty", "tz")

    def __init__(self, dev: PortDevice, top: FloatArray, normal: FloatArray, n_ticks: int) -> None:
        self.dev = dev
        self.x = np.empty(n_ticks)
        self.f = np.empty(n_ticks)
        self.hit = False
        self.nx, self.ny, self.nz = (float(v) for v in normal)
        self.tx, self.ty, self.tz = (float(v) for v in top)

    def __call__(self, n: int) -> None:
        dev = self.dev
        qx, qy, qz = dev.last_read
        fx, fy, fz = dev.applied_force_n
        nx, ny, nz = self.nx, self.ny, self.nz
        self.x[n] = (self.tx - qx) * nx + (self.ty - qy) * ny + (self.tz - qz) * nz
        self.f[n] = fx * nx + fy * ny + fz * nz
        self.hit = self.hit or dev.at_end_stop()


def run_3d_cell(
    scheme: str,
    *,
    stiffness_scale: float = 1.0,
    mesh: str = "balloon",
    delay_ms: float = 0.0,
    trajectory: str = "press",
    device: DeviceModel = DEFAULT_DEVICE,
    hand: HandParams | None = None,
    rendering: Rendering | None = None,
    gain_table: GainTable | None = None,
    direct_reference: DirectReference = DIRECT_REFERENCE,
    rest_plane: bool = True,
) -> Run3D:
    """Run one scheme on the World (module docstring): one user pressing the top.

    Parameters
    ----------
    scheme : str
        One of :data:`haptic_collab.research.fidelity_schemes.SCHEMES`.
    stiffness_scale : float
        ``--stiffness-scale`` of the balloon (1.0: K_o about 310 N/m at the top; 3.3: about
        1000 N/m, the paper's Fig. 10).
    mesh : str
        ``--mesh`` of the object: ``balloon`` (default) or a shape of the stress set
        (:data:`server.objects.shapes.STRESS_MESHES`); ``fem:NAME`` makes it the FEM solid of that
        surface in :data:`haptic_collab.research.harness_3d.FEM_MATERIAL_3D` (``--object fem``). The user presses its top.
    delay_ms : float
        One-way network delay [ms], whole servo ticks, >= 0.
    trajectory : {"press", "impact"}
    device : DeviceModel
        Force, stiffness and damping limits (applied to the simulated Phantom Desktop).
    hand : HandParams, optional
        The simulated hand (default :class:`HandParams`).
    rendering : Rendering, optional
        The scheme's rendering; default :func:`rendering_3d` for the K_o at the top.
    gain_table : GainTable, optional
        Cache of the local models' designs.
    direct_reference : {"undisturbed", "patch"}
        The direct schemes' force rule (module docstring).
    rest_plane : bool
        A local model renders the rest plane the World sends the user alone (default True, as
        the client: :func:`haptic_collab.research.fidelity_users_3d.rendering_3d`); False: its
        design against the current surface.

    Returns
    -------
    Run3D

    Raises
    ------
    ValueError
        An unknown scheme or trajectory, a rendering of another scheme, a delay that is not a
        whole number of servo ticks, a bad scale or direct rule.
    """
    if scheme not in SCHEMES_3D:
        raise ValueError(
            f"unknown scheme {scheme!r} on the World; expected one of {', '.join(SCHEMES_3D)}"
        )
    if trajectory not in TRAJECTORIES_3D:
        raise ValueError(
            f"unknown trajectory {trajectory!r}; expected one of {', '.join(TRAJECTORIES_3D)}"
        )
    if direct_reference not in ("undisturbed", "patch"):
        raise ValueError(
            f"direct_reference must be 'undisturbed' or 'patch', got {direct_reference!r}"
        )
    d = check_delay(delay_ms)
    tr = TRAJECTORIES_3D[trajectory]
    hand = hand if hand is not None else HandParams()
    T = 1.0 / SERVO_RATE_HZ

    world = reused_world(stiffness_scale, mesh)
    out0, top, normal = top_contact(world)
    k_o = float(out0.k_o)
    r = (
        rendering
        if rendering is not None
        else rendering_3d(
            scheme,
            k_o,
            delay_ms,
            device=device,
            gain_table=gain_table,
            rest_plane=rest_plane,
            b_o=float(out0.b_o),
        )
    )
    if r.scheme != scheme:
        raise ValueError(f"rendering is for {r.scheme!r}, not {scheme!r}")

    dev = scheme_device(r, top, normal, tr, device, hand)
    n_ticks = round(tr.duration_s * SERVO_RATE_HZ)
    trace = _Trace(dev, top, normal, n_ticks)
    fmax = device.max_force_n
    world_k_o: list[float] = []

    # what the World sees before tick d: the starting probe, no force
    start = np.asarray(dev.trajectory(0.0), dtype=np.float64)

    if r.kind not in ("coupling", "mmt", "wall", "direct"):
        raise ValueError(f"{scheme} ({r.kind}) is not modelled on the 3-D World")
    user: ServoPort | DirectPort
    if r.kind != "direct":
        core, patch_kw = scheme_servo(r, dev, device, k_o, out0)
        user = ServoPort(core, start, r.i_gain, patch_kw, trace)

        def world_tick(n: int, states: dict[str, Any]) -> dict[str, Any]:
            out = world.tick({USER: states[USER]})[USER]
            world_k_o.append(float(out.k_o))
            return {USER: renewed_patch(r, out, out0)}

    else:
        pc = (
            PassivityController(
                PassivityParams(
                    max_damping_n_s_per_m=(
                        device.max_damping_n_s_per_m
                        if r.passivity_max_damping is None
                        else min(r.passivity_max_damping, UNCAPPED_DAMPING_N_S_PER_M)
                    ),
                    energy_bias_j=r.passivity_bias_j,
                    servo_period_s=T,
                    max_force_n=fmax,
                )
            )
            if r.passivity
            else None
        )
        user = DirectPort(dev, pc, fmax, start, trace)
        last = out0
        f_prev = 0.0

        def world_tick(n: int, states: dict[str, Any]) -> dict[str, Any]:
            # the World's force on the probe it received (module docstring), applied to the object
            nonlocal last, f_prev
            probe = states[USER]
            e, ex, ey, ez = last.primitive.contact(
                float(probe[0]), float(probe[1]), float(probe[2])
            )
            base = f_prev if direct_reference == "undisturbed" else 0.0
            push = min(max(base + last.k_o * e, 0.0), fmax)
            force = np.array([push * ex, push * ey, push * ez], dtype=np.float64)
            last = world.tick({USER: ContactInput(probe=probe, force=force)})[USER]
            world_k_o.append(float(last.k_o))
            f_prev = push
            return {USER: (float(force[0]), float(force[1]), float(force[2]))}

    run_multirate(n_ticks, {USER: user}, world_tick, Timing.network(d, RATE_RATIO))
    x, f, hit = trace.x, trace.f, trace.hit

    t = np.arange(n_ticks, dtype=np.float64) * T
    runaway = bool(
        hit or not np.isfinite(x).all() or not np.isfinite(f).all() or np.abs(x).max() > RUNAWAY_M
    )
    cell = Cell(r, k_o, SIM_RATE_HZ, float(delay_ms), combined_hand(hand, PROFILE), tr)
    run = Run(t=t, x=x[None, :], f=f[None, :], runaway=np.array([runaway]))
    metrics = cell_metrics(run, [cell])[0]
    return Run3D(
        cell=cell,
        stiffness_scale=float(stiffness_scale),
        mesh=mesh,
        t=t,
        x=x,
        f=f,
        runaway=runaway,
        metrics=metrics,
        world_k_o=np.asarray(world_k_o),
    )


def _cell_job(
    scheme: str,
    scale: float,
    mesh: str,
    delay_ms: float,
    trajectory: str,
    device: DeviceModel,
    rendering: Rendering,
    direct_reference: DirectReference,
) -> dict[str, Any]:
    """One cell's JSON (a worker's job)."""
    return run_3d_cell(
        scheme,
        stiffness_scale=scale,
        mesh=mesh,
        delay_ms=delay_ms,
        trajectory=trajectory,
        device=device,
        rendering=rendering,
        direct_reference=direct_reference,
    ).to_json()


def _design_job(
    scheme: str, scale: float, mesh: str, delay_ms: float, device: DeviceModel, rest_plane: bool
) -> Rendering:
    """One scheme's rendering for the K_o at the top of ``mesh`` scaled by ``scale`` (a worker's
    job: a local model's design takes seconds, and so does a FEM solid's start-up, which the
    worker then keeps for its cells: :func:`haptic_collab.research.harness_3d.reused_world`)."""
    return rendering_3d(
        scheme, top_k_o(scale, mesh), delay_ms, device=device, rest_plane=rest_plane
    )


def run_3d_cells(
    schemes: Sequence[str] = SCHEMES_3D,
    *,
    stiffness_scales: Sequence[float] = (1.0, 3.3),
    delays_ms: Sequence[float] = (0.0, 100.0),
    trajectories: Sequence[str] = ("press", "impact"),
    meshes: Sequence[str] = ("balloon",),
    device: DeviceModel = DEFAULT_DEVICE,
    workers: int | None = 1,
    gain_table: GainTable | None = None,
    direct_reference: DirectReference = DIRECT_REFERENCE,
    pool: Executor | None = None,
    rest_plane: bool = True,
) -> list[dict[str, Any]]:
    """Every scheme x mesh x stiffness scale x delay x trajectory on the World (module docstring).

    Parameters
    ----------
    schemes : sequence of str
        Subset of :data:`SCHEMES_3D`.
    stiffness_scales : sequence of float
        Balloon ``--stiffness-scale`` values (> 0).
    delays_ms : sequence of float
        One-way delays [ms], whole servo ticks.
    trajectories : sequence of {"press", "impact"}
    meshes : sequence of str
        Objects (``--mesh``): ``balloon`` and shapes of the stress set
        (:data:`server.objects.shapes.STRESS_MESHES`), ``fem:NAME`` for the FEM solid of one;
        each cell's K_o is the mesh's at its top.
    device : DeviceModel
    workers : int or None
        Worker processes (spawn) for the designs and the runs; 1 (default) runs in this process,
        None uses every core. The result does not depend on it.
    gain_table : GainTable, optional
        Cache of the local models' designs (in-process runs only).
    direct_reference : {"undisturbed", "patch"}
        The direct schemes' force rule.
    pool : Executor, optional
        Run the designs and the cells there (``workers`` unused), and leave it open: a caller
        running several grids keeps its workers, their imports and the objects they built.
    rest_plane : bool
        The local models render the rest plane the World sends the user alone (default True, as
        the client; :func:`haptic_collab.research.fidelity_users_3d.rendering_3d`); False: their
        designs against the current surface.

    Returns
    -------
    list of dict
        One cell per combination, in the order scheme, scale, delay, trajectory: ``scheme``,
        ``model`` (``"3d"``), ``k_o_n_per_m`` (K_o at the top), ``sim_rate_hz`` (20),
        ``delay_ms``, ``hand`` (hand + device as the probe feels them: ``mass_kg``,
        ``stiffness_n_per_m``, ``damping_n_s_per_m``), ``trajectory``, ``stiffness_scale``, the
        :class:`haptic_collab.research.fidelity_metrics.CellMetrics` fields, and ``felt_stiffness_ratio_1hz`` /
        ``_8hz`` (None: measured in 1-D only).

    Raises
    ------
    ValueError
        An unknown scheme or trajectory, a bad scale or delay, or ``workers < 1``.
    """
    check_known(schemes, SCHEMES_3D, "scheme")
    check_known(trajectories, tuple(TRAJECTORIES_3D), "trajectory")
    check_runs(delays_ms, workers)
    combos = [
        (s, sc, m, dm, name)
        for s in schemes
        for m in meshes
        for sc in stiffness_scales
        for dm in delays_ms
        for name in trajectories
    ]
    rend_keys = sorted({(s, sc, m, dm) for s, sc, m, dm, _ in combos}, key=str)
    if workers == 1 and pool is None:
        k_o = {(sc, m): top_k_o(sc, m) for m in meshes for sc in stiffness_scales}
        table = gain_table if gain_table is not None else GainTable()
        rend = {
            (s, sc, m, dm): rendering_3d(
                s, k_o[(sc, m)], dm, device=device, gain_table=table, rest_plane=rest_plane
            )
            for s, sc, m, dm in rend_keys
        }
        return [
            _cell_job(s, sc, m, dm, name, device, rend[(s, sc, m, dm)], direct_reference)
            for s, sc, m, dm, name in combos
        ]
    with executor(pool, workers) as ex:
        fut_r = {
            (s, sc, m, dm): ex.submit(_design_job, s, sc, m, dm, device, rest_plane)
            for s, sc, m, dm in rend_keys
        }
        rend = {k: v.result() for k, v in fut_r.items()}
        futs = [
            ex.submit(_cell_job, s, sc, m, dm, name, device, rend[(s, sc, m, dm)], direct_reference)
            for s, sc, m, dm, name in combos
        ]
        return [fu.result() for fu in futs]
