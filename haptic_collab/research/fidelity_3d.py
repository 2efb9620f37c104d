"""The fidelity benchmark's schemes on the 3-D World: the product's own object, servo and hand.

Issue 9 (``haptic bench fidelity``): the 1-D multirate simulator of :mod:`haptic_collab.research.fidelity_1d` carries
the full grid; the same schemes also run here on the server's :class:`server.world.World`
(the default water balloon, ``--stiffness-scale``, 20 Hz) without the network, one user pressing
the top with the default simulated hand. Every block is the product's code run in-process, tick
by tick, with integer ticks and no clock, socket or thread (as :mod:`haptic_collab.research.reproduce_3d`):

object
    :func:`server.main.build_world` with ``ServerOptions(sim_rate_hz=20,
    stiffness_scale=s)``, stepped once every N = 50 servo ticks. K_o is what the World reports
    at the top for a probe resting on it with no force (the first World tick of a run:
    :func:`top_contact`); that tick's :class:`server.world.ContactOutput` is also the patch the
    user holds before the run starts (the 1-D servo likewise knows the rest surface at t = 0).
user
    :class:`client.devices.sim.SimDevice`, profile ``phantom-desktop`` with the
    :class:`haptic_collab.research.fidelity_1d.DeviceModel`'s force, stiffness and damping limits, default
    :class:`client.devices.sim.HandParams`; the hand target moves along the top's inward normal
    exactly as the 1-D trajectory ``y(t)`` (:class:`NormalTrajectory`); for ``impact`` the handle
    starts with the hand's velocity, as in the 1-D model. The probe hitting the device's
    workspace end stop counts as a runaway (the 1-D model's :data:`haptic_collab.research.fidelity_1d.RUNAWAY_M`
    cannot be reached inside the 120 mm workspace).
network
    one-way delay ``d`` whole servo ticks both ways, as the 1-D model: the World ticking at servo
    tick ``n`` (``n % N == 0``) uses the user's state published by the servo at tick ``n - d``
    (the client is modelled as sending its latest state every tick; the product's client sends
    it every half simulation period), and its output reaches the servo from tick ``n + 1 + d``.
    Before tick ``d`` the World sees the user's starting probe and no force.

Schemes (:func:`haptic_collab.research.fidelity_1d.rendering_for` for the gains):

``local-p``, ``local-pi``, ``mmt``, ``static-local`` (:data:`SCHEMES_3D`)
    :class:`client.servo.ServoCore` at 1 kHz rendering the World's patch with the scheme's
    K_h, I, B_h, proxy hold (``hold_ticks = N``) and own-force compensation (the patch moved out by
    C_h times the World's ``own_force_n``, as the client's
    :meth:`shared.local_model_update.LocalModelUpdate.from_wire`); the World receives the probe and the force
    the servo rendered (Step 3 of the paper's section 6). The local models' gains are the
    product's design for the K_o at the top and the delay ticks the client would measure
    (:class:`shared.gain_design.GainTable`, margin 0.15, K_h <= the device's maximum stiffness,
    B_h <= its maximum damping); eq. 17 threshold fixed at 1 mm, release over two simulation
    periods, integral limited to the device's maximum force; passivity layer on for PI
    (``ServoConfig(passivity=True)``, 1 mJ bias). Two safety features of the servo that the 1-D
    model does not have are set out of the way so that the schemes are compared as control laws:
    the force ramp at start-up is one tick (``ramp_s = T``) and the velocity limit is raised to
    :data:`VELOCITY_LIMIT_M_S`; the device's stiffness limit is raised to K_h when K_h is above it
    (as :mod:`haptic_collab.research.reproduce_3d` does). ``mmt`` renders each patch moved out by the World's
    own-force deformation ``F / K_o`` (the rest surface it estimates) with that tick's K_o
    (capped at the device's stiffness) and its damper; ``static-local`` keeps the first patch (the
    rest surface) with the K_o at the top. The virtual coupling's tool and the force-jacobian
    need a simulation side the World does not have: they run in 1-D only.
``direct``, ``direct-tdpa``
    the World computes the contact force from the probe it received, applies it to the object
    as the user's contact force and sends it back; the user's loop (written here: read the
    device, write the force) holds it (zero-order hold) until the next one. The rule (see
    :data:`DIRECT_REFERENCE`): with ``(prim, K_o)`` the World's last :class:`ContactOutput` for
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

Metrics (:func:`haptic_collab.research.fidelity_1d.cell_metrics`) are taken on ``x`` = the probe position read by
the servo, as depth below the rest top along the inward normal [m], and ``f`` = the force written
to the device along the top's outward normal [N] (positive pushing the probe out), on the servo
clock ``t = n T`` with the windows of the matching :data:`haptic_collab.research.fidelity_1d.PRESS` /
:data:`haptic_collab.research.fidelity_1d.IMPACT`.

Two users (:func:`run_3d_pairs`): the same blocks twice on one World, the demo's scene. B rests
on the balloon's side (:data:`PAIR_REST`) while A presses its top from 3 s (:data:`PAIR_PRESS`);
what B feels of A's press is compared with what a probe held still there would feel
(:class:`Pair3D`). Only the schemes whose servo renders a patch run there (:data:`PAIR_SCHEMES`).

Usage::

    from haptic_collab.research.fidelity_3d import run_3d_cells
    cells = run_3d_cells(("local-p", "direct"), stiffness_scales=(3.3,), delays_ms=(100.0,))
"""

from __future__ import annotations

import math
import multiprocessing as mp
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from haptic_collab.client.devices.base import Vec3
from haptic_collab.client.devices.profiles import get_sim_profile
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.research.fidelity_1d import (
    IMPACT,
    PRESS,
    RUNAWAY_M,
    SCHEMES,
    Cell,
    CellMetrics,
    DeviceModel,
    Rendering,
    Run,
    Trajectory,
    cell_metrics,
    design_delay_ticks,
    rendering_for,
)
from haptic_collab.research.reproduce_3d import combined_hand
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import object_info
from haptic_collab.server.world import ContactInput, ContactOutput, World
from haptic_collab.shared.gain_design import GainTable
from haptic_collab.shared.gain_key import GainKey
from haptic_collab.shared.local_model import LocalModelParams, ThresholdParams
from haptic_collab.shared.passivity import PassivityController, PassivityParams
from haptic_collab.shared.primitives import Plane, Sphere, moved_out
from haptic_collab.shared.types import FloatArray

DirectReference = Literal["undisturbed", "patch"]

#: Servo rate 1/T [Hz].
SERVO_RATE_HZ = 1000.0
#: World rate [Hz] (issue 9: the 3-D cells run at 20 Hz).
SIM_RATE_HZ = 20.0
#: Servo ticks per World tick.
RATE_RATIO = round(SERVO_RATE_HZ / SIM_RATE_HZ)
#: The simulated device.
PROFILE = "phantom-desktop"
#: The servo's velocity limit [m/s] during these runs (the 1-D model has none; the product's
#: 0.6 m/s would withhold forces on a fast impact or an oscillating scheme).
VELOCITY_LIMIT_M_S = 100.0
#: The damping cap [N*s/m] standing in for "uncapped" in the servo's passivity controller (which
#: needs a finite one): far above anything the 7.9 N force clamp lets act.
UNCAPPED_DAMPING_N_S_PER_M = 1e6
#: The schemes the World cells run: those whose simulation side the World has (the virtual
#: coupling's tool equilibrium and the force-jacobian's stiffness about the received probe are
#: modelled in 1-D only).
SCHEMES_3D: tuple[str, ...] = tuple(
    s for s in SCHEMES if s not in ("virtual-coupling", "force-jacobian")
)
#: Default rule of the direct schemes (module docstring).
DIRECT_REFERENCE: DirectReference = "undisturbed"
#: The 3-D trajectories, by name, with the 1-D windows their metrics use.
TRAJECTORIES_3D: dict[str, Trajectory] = {"press": PRESS, "impact": IMPACT}
#: The device every scheme renders on by default (the simulated Phantom Desktop's limits).
DEFAULT_DEVICE = DeviceModel()
#: Design margin and other fixed parts of the client's gain key (as :mod:`haptic_collab.bench.fidelity`).
DESIGN_MARGIN = 0.15

_USER = "user"


#: Prefix of a mesh name that makes the object the FEM solid of that surface (``--object fem``),
#: in :data:`FEM_MATERIAL_3D`: ``fem:box`` is the stress set's box as a liver-like solid.
FEM_PREFIX = "fem:"
#: The solid material of the FEM cells (:mod:`server.solid_materials`).
FEM_MATERIAL_3D = "liver"


def _opts(stiffness_scale: float, mesh: str = "balloon") -> ServerOptions:
    if mesh.startswith(FEM_PREFIX):
        return ServerOptions(
            sim_rate_hz=SIM_RATE_HZ,
            stiffness_scale=stiffness_scale,
            object="fem",
            mesh=mesh[len(FEM_PREFIX) :],
            material=FEM_MATERIAL_3D,
        )
    return ServerOptions(sim_rate_hz=SIM_RATE_HZ, stiffness_scale=stiffness_scale, mesh=mesh)


def top_contact(world: World) -> tuple[ContactOutput, FloatArray, FloatArray]:
    """One World tick with the user's probe exactly at the top of the rest surface, no force.

    The top is the demo's (:func:`server.room.object_info`): the highest vertex nearest the
    vertical axis of the bounding box (the balloon's pole, the middle of a box's top face, a
    torus's ring rather than its hole).

    Returns
    -------
    (output, top, normal)
        The user's :class:`ContactOutput` (K_o at the top, the rest-surface patch), the top
        point (3,) [m] and the outward unit normal (3,) there (the patch's).
    """
    info = object_info(world.vertices, world.faces)
    top = np.array(info.top_m, dtype=np.float64)
    out = world.tick({_USER: ContactInput(probe=top, force=np.zeros(3))})[_USER]
    n = np.asarray(out.normal, dtype=np.float64)
    return out, top, n / float(np.linalg.norm(n))


def top_k_o(stiffness_scale: float, mesh: str = "balloon") -> float:
    """K_o [N/m] the World reports at the top of ``mesh`` scaled by ``stiffness_scale``.

    Raises
    ------
    ValueError
        A scale that is not a finite number > 0 (:func:`server.main.build_world`).
    """
    out, _, _ = top_contact(build_world(_opts(stiffness_scale, mesh)))
    return float(out.k_o)


class NormalTrajectory:
    """The 1-D intention ``y(t)`` (:class:`haptic_collab.research.fidelity_1d.Trajectory`) as a hand target in 3-D.

    ``target(t) = top - y(t) normal`` [m] (``y`` positive inside), the callable
    :class:`client.devices.sim.SimDevice` pulls the hand toward; tabulated on the servo ticks
    ``t = n / servo_rate_hz`` of the trajectory's duration and linearly interpolated between them
    (held after the end).

    Parameters
    ----------
    trajectory : Trajectory
    top, normal : (3,) float
        Rest top [m] and its outward unit normal.
    servo_rate_hz : float
    """

    def __init__(
        self,
        trajectory: Trajectory,
        top: ArrayLike,
        normal: ArrayLike,
        servo_rate_hz: float = SERVO_RATE_HZ,
    ) -> None:
        self.trajectory = trajectory
        self._top = np.asarray(top, dtype=np.float64).reshape(3)
        self._n = np.asarray(normal, dtype=np.float64).reshape(3)
        self._T = 1.0 / float(servo_rate_hz)
        n = round(trajectory.duration_s * servo_rate_hz) + 1
        self._t = np.arange(n, dtype=np.float64) * self._T
        y, yd = trajectory.target(self._t)
        self._y = np.asarray(y, dtype=np.float64)
        self.initial_speed_in_m_s = float(yd[0])

    def depth_m(self, t_s: float) -> float:
        """Intended depth ``y`` [m] at ``t_s`` [s]."""
        k = t_s / self._T
        i = round(k)
        if abs(k - i) < 1e-9 and 0 <= i < len(self._y):
            return float(self._y[i])
        return float(np.interp(t_s, self._t, self._y))

    @property
    def initial_velocity_m_s(self) -> Vec3:
        """The hand's velocity (3,) [m/s] at t = 0 (an impact starts already moving)."""
        v = -self.initial_speed_in_m_s * self._n
        return (float(v[0]), float(v[1]), float(v[2]))

    def __call__(self, t_s: float) -> Vec3:
        """Hand target (x, y, z) [m] at ``t_s`` [s]."""
        p = self._top - self.depth_m(t_s) * self._n
        return (float(p[0]), float(p[1]), float(p[2]))


class _PortDevice(SimDevice):
    """A :class:`SimDevice` whose handle starts with a given velocity and that remembers the
    position the servo last read (the 1-D model's ``x``).

    SimDevice has no public way to start the handle moving: this sets its velocity state
    (``_v``) right after the first read, which places the handle (``_t`` is None before it).
    """

    def __init__(self, *args: Any, initial_velocity: Vec3 = (0.0, 0.0, 0.0), **kw: Any) -> None:
        super().__init__(*args, **kw)
        self._v_start = initial_velocity
        self.last_read: Vec3 = (math.nan, math.nan, math.nan)

    def read(self, t_s: float) -> Vec3:
        first = self._t is None
        q = super().read(t_s)
        if first:
            self._v = self._v_start  # the hand already moving with its intention (1-D: v = y')
        self.last_read = q
        return q

    def at_end_stop(self) -> bool:
        """The handle is on a face of the workspace box (the device's mechanical stop)."""
        x, lo, hi = self.position_m, self.limits.workspace_min_m, self.limits.workspace_max_m
        return any(x[i] <= lo[i] or x[i] >= hi[i] for i in range(3))


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
        solid of that surface, :data:`FEM_PREFIX`).
    t : (n,) float
        Servo tick times [s].
    x : (n,) float
        Probe depth [m] below the rest top along the inward normal, as read by the servo.
    f : (n,) float
        Force [N] written to the device along the top's outward normal (pushing the probe out).
    runaway : bool
        The probe reached the workspace end stop, left :data:`haptic_collab.research.fidelity_1d.RUNAWAY_M` or went
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


def gain_key(mode: Literal["p", "pi"], delay_ms: float, device: DeviceModel) -> GainKey:
    """The client's gain key at 20 Hz for a one-way delay ``delay_ms`` [ms] (the 1-D bench's)."""
    return GainKey(
        servo_rate_hz=SERVO_RATE_HZ,
        sim_rate_hz=SIM_RATE_HZ,
        delay_ticks=design_delay_ticks(delay_ms * 1e-3, SIM_RATE_HZ),
        mode=mode,
        margin=DESIGN_MARGIN,
        k_h_max=device.max_stiffness_n_per_m,
        b_h_max=device.max_damping_n_s_per_m,
    )


def rendering_3d(
    scheme: str,
    k_o: float,
    delay_ms: float,
    *,
    device: DeviceModel = DEFAULT_DEVICE,
    gain_table: GainTable | None = None,
) -> Rendering:
    """:func:`haptic_collab.research.fidelity_1d.rendering_for` at 20 Hz, designing the local models' gains for
    ``k_o`` [N/m] and ``delay_ms`` [ms] (seconds per design; ``gain_table`` caches them).

    Raises
    ------
    ValueError
        An unknown scheme, or a K_o the design refuses.
    """
    design = None
    if scheme in ("local-p", "local-pi"):
        mode: Literal["p", "pi"] = "pi" if scheme == "local-pi" else "p"
        table = gain_table if gain_table is not None else GainTable()
        key = gain_key(mode, delay_ms, device)
        design = table.lookup(key, k_o)
        if design is None:
            design = table.design(key, k_o)
    return rendering_for(scheme, sim_rate_hz=SIM_RATE_HZ, device=device, design=design, k_o=k_o)


def _device(
    r: Rendering,
    point: FloatArray,
    normal: FloatArray,
    tr: Trajectory,
    device: DeviceModel,
    hand: HandParams,
) -> _PortDevice:
    """The simulated Phantom Desktop of one user, its workspace centred on ``point`` and its hand
    following ``tr`` along ``normal`` (module docstring), opened with forces enabled."""
    prof = get_sim_profile(PROFILE)
    limits = replace(
        prof.limits,
        max_force_n=device.max_force_n,
        max_stiffness_n_per_m=max(device.max_stiffness_n_per_m, r.k_h),
        max_damping_n_s_per_m=device.max_damping_n_s_per_m,
        max_velocity_m_s=VELOCITY_LIMIT_M_S,
        # the schemes are compared on their loops over seconds-long presses, as the 1-D model
        # compares them: no motor-heating limit (client/thermal.py) lowers any scheme's force
        max_continuous_force_n=None,
    ).centered_at((float(point[0]), float(point[1]), float(point[2])))
    target = NormalTrajectory(tr, point, normal)
    dev = _PortDevice(
        prof,
        target,
        hand,
        limits=limits,
        servo_period_s=1.0 / SERVO_RATE_HZ,
        initial_velocity=target.initial_velocity_m_s,
    )
    dev.open()
    dev.enable_forces()
    return dev


def _servo(
    r: Rendering, dev: _PortDevice, device: DeviceModel, k_o: float, out0: ContactOutput
) -> tuple[ServoCore, dict[str, Any]]:
    """The servo loop of a servo-side scheme on ``dev``, holding the rest patch ``out0``, with
    the keyword arguments of its later ``set_patch`` calls (module docstring)."""
    T = 1.0 / SERVO_RATE_HZ
    lm = LocalModelParams(
        k_h=r.k_h,
        i_gain=r.i_gain,
        servo_period_s=T,
        threshold=ThresholdParams(mode="fixed", theta_m=r.theta_m),
        release_time_s=r.release_time_s,
        integral_limit_n=device.max_force_n,
    )
    cfg = ServoConfig(
        servo_rate_hz=SERVO_RATE_HZ,
        ramp_s=T,
        passivity=r.passivity,
        passivity_energy_bias_j=r.passivity_bias_j if r.passivity else 1e-3,
    )
    core = ServoCore(dev, cfg, local_model=lm, recorder=TelemetryRecorder(capacity=64))
    patch_kw: dict[str, Any] = {
        "b_h": r.b_h,
        "proxy_hold": r.proxy_hold,
        "hold_ticks": RATE_RATIO,
        "k_o": k_o,
    }
    k_h0 = min(r.k_h, k_o) if r.kind == "mmt" else r.k_h
    core.set_patch(out0.primitive, k_h0, r.i_gain, **patch_kw)
    core.enable_forces()
    return core, patch_kw


def _renewed_patch(
    r: Rendering, out: ContactOutput, out0: ContactOutput
) -> tuple[Plane | Sphere, float]:
    """The patch and K_h [N/m] a servo-side scheme renders after a World tick gave ``out``
    (``out0``: the user's first output, the rest surface)."""
    if r.kind == "mmt":
        # the rest surface and stiffness the World estimates: its patch less its own
        # deformation F / K_o, rendered with that K_o (capped)
        k_est = float(out.k_o)
        return moved_out(out.primitive, out.own_force_n / k_est), min(r.k_h, k_est)
    if r.kind == "coupling":
        # own-force compensation: the surface moved out by C_h times the force applied
        return moved_out(out.primitive, r.own_gain * out.own_force_n), r.k_h
    # a wall keeps the rest surface it started with, sent afresh each tick (the servo ramps out
    # a patch that is not renewed)
    return out0.primitive, r.k_h


def _check_known(names: Sequence[str], known: Sequence[str], what: str) -> None:
    for name in names:
        if name not in known:
            raise ValueError(f"unknown {what} {name!r}; expected one of {', '.join(known)}")


def _check_runs(delays_ms: Sequence[float], workers: int | None) -> None:
    for dm in delays_ms:
        _check_delay(dm)
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers!r}")


def _check_delay(delay_ms: float) -> int:
    dq = delay_ms * 1e-3 * SERVO_RATE_HZ
    if not (math.isfinite(delay_ms) and delay_ms >= 0.0 and abs(dq - round(dq)) < 1e-9):
        raise ValueError(f"delay must be whole servo ticks >= 0 ms, got {delay_ms!r}")
    return round(dq)


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
) -> Run3D:
    """Run one scheme on the World (module docstring): one user pressing the top.

    Parameters
    ----------
    scheme : str
        One of :data:`haptic_collab.research.fidelity_1d.SCHEMES`.
    stiffness_scale : float
        ``--stiffness-scale`` of the balloon (1.0: K_o about 310 N/m at the top; 3.3: about
        1000 N/m, the paper's Fig. 10).
    mesh : str
        ``--mesh`` of the object: ``balloon`` (default) or a shape of the stress set
        (:data:`server.objects.shapes.STRESS_MESHES`); ``fem:NAME`` makes it the FEM solid of that
        surface in :data:`FEM_MATERIAL_3D` (``--object fem``). The user presses its top.
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
    d = _check_delay(delay_ms)
    tr = TRAJECTORIES_3D[trajectory]
    hand = hand if hand is not None else HandParams()
    T = 1.0 / SERVO_RATE_HZ
    N = RATE_RATIO

    world = build_world(_opts(stiffness_scale, mesh))
    out0, top, normal = top_contact(world)
    k_o = float(out0.k_o)
    r = (
        rendering
        if rendering is not None
        else rendering_3d(scheme, k_o, delay_ms, device=device, gain_table=gain_table)
    )
    if r.scheme != scheme:
        raise ValueError(f"rendering is for {r.scheme!r}, not {scheme!r}")

    dev = _device(r, top, normal, tr, device, hand)
    n_ticks = round(tr.duration_s * SERVO_RATE_HZ)
    x = np.empty(n_ticks)
    f = np.empty(n_ticks)
    hit = False
    nx, ny, nz = (float(v) for v in normal)
    tx, ty, tz = (float(v) for v in top)
    fmax = device.max_force_n
    world_k_o: list[float] = []

    # what the World sees before tick d: the starting probe, no force
    start = np.asarray(dev.trajectory(0.0), dtype=np.float64)

    if r.kind not in ("coupling", "mmt", "wall", "direct"):
        raise ValueError(f"{scheme} ({r.kind}) is not modelled on the 3-D World")
    if r.kind != "direct":
        core, patch_kw = _servo(r, dev, device, k_o, out0)
        sent: dict[int, ContactInput] = {}
        patches: dict[int, tuple[Plane | Sphere, float]] = {}
        for n in range(n_ticks):
            new = patches.pop(n, None)
            if new is not None:
                core.set_patch(new[0], new[1], r.i_gain, **patch_kw)
            core.tick(n * T)
            qx, qy, qz = dev.last_read
            fx, fy, fz = dev.applied_force_n
            x[n] = (tx - qx) * nx + (ty - qy) * ny + (tz - qz) * nz
            f[n] = fx * nx + fy * ny + fz * nz
            hit = hit or dev.at_end_stop()
            if (n + d) % N == 0:
                snap = core.latest()
                if snap is not None:
                    sent[n + d] = ContactInput(
                        probe=np.asarray(snap.probe_m, dtype=np.float64),
                        force=np.asarray(snap.force_n, dtype=np.float64),
                    )
            if n % N == 0:
                state = sent.pop(n, None)
                if state is None:
                    state = ContactInput(probe=start, force=np.zeros(3))
                out = world.tick({_USER: state})[_USER]
                world_k_o.append(float(out.k_o))
                patches[n + 1 + d] = _renewed_patch(r, out, out0)
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
        probes: dict[int, FloatArray] = {}
        forces: dict[int, Vec3] = {}
        last = out0
        f_prev = 0.0
        held: Vec3 = (0.0, 0.0, 0.0)
        px = py = pz = math.nan
        for n in range(n_ticks):
            arrived = forces.pop(n, None)
            if arrived is not None:
                held = arrived
            qx, qy, qz = dev.read(n * T)
            hx, hy, hz = held
            if pc is not None:
                if n:
                    vx, vy, vz = (qx - px) / T, (qy - py) / T, (qz - pz) / T
                else:  # no backward difference yet (the 1-D model's first tick too)
                    vx = vy = vz = 0.0
                hx, hy, hz = pc.step(hx, hy, hz, vx, vy, vz)
            m2 = hx * hx + hy * hy + hz * hz
            if m2 > fmax * fmax:
                s = fmax / math.sqrt(m2)
                hx, hy, hz = hx * s, hy * s, hz * s
            dev.write(hx, hy, hz)
            px, py, pz = qx, qy, qz
            fx, fy, fz = dev.applied_force_n
            x[n] = (tx - qx) * nx + (ty - qy) * ny + (tz - qz) * nz
            f[n] = fx * nx + fy * ny + fz * nz
            hit = hit or dev.at_end_stop()
            if (n + d) % N == 0:
                probes[n + d] = np.array([qx, qy, qz], dtype=np.float64)
            if n % N == 0:
                probe = probes.pop(n, start)
                e, ex, ey, ez = last.primitive.contact(
                    float(probe[0]), float(probe[1]), float(probe[2])
                )
                base = f_prev if direct_reference == "undisturbed" else 0.0
                push = min(max(base + last.k_o * e, 0.0), fmax)
                force = np.array([push * ex, push * ey, push * ez], dtype=np.float64)
                last = world.tick({_USER: ContactInput(probe=probe, force=force)})[_USER]
                world_k_o.append(float(last.k_o))
                f_prev = push
                forces[n + 1 + d] = (float(force[0]), float(force[1]), float(force[2]))

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
#: A's intention: :data:`haptic_collab.research.fidelity_1d.PRESS` (10 mm into the top) started at 3 s, held to 8 s.
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
    _check_known((scheme,), PAIR_SCHEMES, "two-user scheme")
    d = _check_delay(delay_ms)
    T, N = 1.0 / SERVO_RATE_HZ, RATE_RATIO
    world = build_world(_opts(stiffness_scale, mesh))
    info = object_info(world.vertices, world.faces)
    points = {"a": np.array(info.top_m, dtype=np.float64), "b": side_point(world)}
    out0 = world.tick({u: ContactInput(probe=p, force=np.zeros(3)) for u, p in points.items()})
    trs = {"a": PAIR_PRESS, "b": PAIR_REST}
    users = {}
    for u in ("a", "b"):
        nrm = np.asarray(out0[u].normal, dtype=np.float64)
        nrm = nrm / float(np.linalg.norm(nrm))
        k_o = float(out0[u].k_o)
        r = rendering_3d(scheme, k_o, delay_ms, device=device, gain_table=gain_table)
        dev = _device(r, points[u], nrm, trs[u], device, HandParams())
        core, kw = _servo(r, dev, device, k_o, out0[u])
        users[u] = (r, dev, core, kw, nrm, np.asarray(dev.trajectory(0.0), dtype=np.float64))
    n_ticks = round(PAIR_DURATION_S * SERVO_RATE_HZ)
    x = {u: np.empty(n_ticks) for u in users}
    f = {u: np.empty(n_ticks) for u in users}
    sent: dict[str, dict[int, ContactInput]] = {u: {} for u in users}
    patches: dict[str, dict[int, tuple[Plane | Sphere, float]]] = {u: {} for u in users}
    surf_t: list[float] = []
    surf_b: list[float] = []
    rest_b: list[float] = []
    hit = False
    bx, by, bz = (float(c) for c in points["b"])
    for n in range(n_ticks):
        for u, (r, dev, core, kw, nrm, _) in users.items():
            new = patches[u].pop(n, None)
            if new is not None:
                core.set_patch(new[0], new[1], r.i_gain, **kw)
            core.tick(n * T)
            q = np.asarray(dev.last_read, dtype=np.float64)
            x[u][n] = float(np.dot(points[u] - q, nrm))
            f[u][n] = float(np.dot(np.asarray(dev.applied_force_n), nrm))
            hit = hit or dev.at_end_stop()
            if (n + d) % N == 0:
                snap = core.latest()
                if snap is not None:
                    sent[u][n + d] = ContactInput(
                        probe=np.asarray(snap.probe_m, dtype=np.float64),
                        force=np.asarray(snap.force_n, dtype=np.float64),
                    )
        if n % N == 0:
            states = {
                u: sent[u].pop(n) if n in sent[u] else ContactInput(users[u][5], np.zeros(3))
                for u in users
            }
            out = world.tick(states)
            for u, (r, *_rest) in users.items():
                patches[u][n + 1 + d] = _renewed_patch(r, out[u], out0[u])
            ob = out["b"]
            surf_t.append(n * T)
            surf_b.append(ob.primitive.contact(bx, by, bz)[0])
            rest = moved_out(ob.primitive, ob.own_force_n / float(ob.k_o))
            rest_b.append(rest.contact(bx, by, bz)[0])
    t = np.arange(n_ticks, dtype=np.float64) * T
    rw = (t >= PAIR_REST_WINDOW_S[0]) & (t < PAIR_REST_WINDOW_S[1])
    hw = (t >= PAIR_HOLD_WINDOW_S[0]) & (t < PAIR_HOLD_WINDOW_S[1])
    ts = np.asarray(surf_t)
    srw = (ts >= PAIR_REST_WINDOW_S[0]) & (ts < PAIR_REST_WINDOW_S[1])
    shw = (ts >= PAIR_HOLD_WINDOW_S[0]) & (ts < PAIR_HOLD_WINDOW_S[1])
    sb, rb = np.asarray(surf_b), np.asarray(rest_b)
    finite = all(np.isfinite(v).all() for v in (*x.values(), *f.values()))
    runaway = bool(hit or not finite)
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
) -> list[dict[str, Any]]:
    """Every two-user cell (:func:`run_3d_pair`) of ``schemes`` x mesh x scale x delay: the
    balloon and the box as a FEM solid by default.

    ``workers`` as :func:`run_3d_cells` (each cell designs its own two renderings). Returns each
    cell's :meth:`Pair3D.to_json`, in the order scheme, mesh, scale, delay.

    Raises
    ------
    ValueError
        A scheme not in :data:`PAIR_SCHEMES`, a bad delay, or ``workers < 1``.
    """
    _check_known(schemes, PAIR_SCHEMES, "two-user scheme")
    _check_runs(delays_ms, workers)
    combos = [
        (s, m, sc, dm)
        for s in schemes
        for m in meshes
        for sc in stiffness_scales
        for dm in delays_ms
    ]
    if workers == 1:
        return [_pair_job(*c, device) for c in combos]
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
        futs = [pool.submit(_pair_job, *c, device) for c in combos]
        return [fu.result() for fu in futs]


def _pair_job(
    scheme: str, mesh: str, scale: float, delay_ms: float, device: DeviceModel
) -> dict[str, Any]:
    """One two-user cell's JSON (a worker's job)."""
    return run_3d_pair(
        scheme, mesh=mesh, stiffness_scale=scale, delay_ms=delay_ms, device=device
    ).to_json()


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


def _design_job(scheme: str, k_o: float, delay_ms: float, device: DeviceModel) -> Rendering:
    """One local model's rendering (a worker's job: the design takes seconds)."""
    return rendering_3d(scheme, k_o, delay_ms, device=device)


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

    Returns
    -------
    list of dict
        One cell per combination, in the order scheme, scale, delay, trajectory: ``scheme``,
        ``model`` (``"3d"``), ``k_o_n_per_m`` (K_o at the top), ``sim_rate_hz`` (20),
        ``delay_ms``, ``hand`` (hand + device as the probe feels them: ``mass_kg``,
        ``stiffness_n_per_m``, ``damping_n_s_per_m``), ``trajectory``, ``stiffness_scale``, the
        :class:`haptic_collab.research.fidelity_1d.CellMetrics` fields, and ``felt_stiffness_ratio_1hz`` /
        ``_8hz`` (None: measured in 1-D only).

    Raises
    ------
    ValueError
        An unknown scheme or trajectory, a bad scale or delay, or ``workers < 1``.
    """
    _check_known(schemes, SCHEMES_3D, "scheme")
    _check_known(trajectories, tuple(TRAJECTORIES_3D), "trajectory")
    _check_runs(delays_ms, workers)
    k_o = {(sc, m): top_k_o(sc, m) for m in meshes for sc in stiffness_scales}
    combos = [
        (s, sc, m, dm, name)
        for s in schemes
        for m in meshes
        for sc in stiffness_scales
        for dm in delays_ms
        for name in trajectories
    ]
    rend_keys = sorted({(s, sc, m, dm) for s, sc, m, dm, _ in combos}, key=str)
    if workers == 1:
        table = gain_table if gain_table is not None else GainTable()
        rend = {
            (s, sc, m, dm): rendering_3d(s, k_o[(sc, m)], dm, device=device, gain_table=table)
            for s, sc, m, dm in rend_keys
        }
        return [
            _cell_job(s, sc, m, dm, name, device, rend[(s, sc, m, dm)], direct_reference)
            for s, sc, m, dm, name in combos
        ]
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
        fut_r = {
            (s, sc, m, dm): pool.submit(_design_job, s, k_o[(sc, m)], dm, device)
            for s, sc, m, dm in rend_keys
        }
        rend = {k: v.result() for k, v in fut_r.items()}
        futs = [
            pool.submit(
                _cell_job, s, sc, m, dm, name, device, rend[(s, sc, m, dm)], direct_reference
            )
            for s, sc, m, dm, name in combos
        ]
        return [fu.result() for fu in futs]
