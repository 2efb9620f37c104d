"""Reproduce Fig. 10 and 11 of Barbagli, Prattichizzo & Salisbury (IJRR 2005) on the 3-D balloon.

Section 7 of the paper: a proportional local model on a Phantom Desktop touching a triangle-mesh
deformable object with K_o = 1.0 N/mm at the contact. K_h = 0.6 and 0.7 N/mm (Fig. 10) are
stable; K_h = 1.2 N/mm (Fig. 11) violates eq. (8) and is unstable.

Here every block is the product's own code, run in-process, tick by tick, with no clock and no
network (integer ticks; time is ``tick / rate``):

- the object: the server's :class:`server.world.World` around the default water balloon, built by
  :func:`server.main.build_world` with ``--stiffness-scale`` chosen so that K_o at the top is
  1000 N/m (the scale is computed from the unscaled K_o at the top), stepped at 20 Hz;
- the user: :class:`client.devices.sim.SimDevice` with the default :class:`HandParams` on the
  ``phantom-desktop`` profile, its hand following a :class:`client.devices.trajectories.Press`
  that approaches the top and presses the probe about 10 mm in, then holds;
- the haptic loop: :class:`client.servo.ServoCore` ticked at 1 kHz with an injected time.

Every simulation tick (50 servo ticks), exactly as :meth:`server.room.Room.tick` does, the
user's latest probe and rendered force (:meth:`ServoCore.latest`) go into
:class:`server.world.ContactInput`; :meth:`World.tick` steps the object and fits the local model,
and its :class:`server.world.ContactOutput` primitive with the case's gains is handed to
:meth:`ServoCore.set_patch` before the next servo tick (zero-order hold on the block boundary,
eq. 1, no extra delay).

Each case is judged three ways: the simulation loop (eq. 8 for P, eq. 15 for PI; the probe as a
position source), the full loop with the hand (:func:`shared.full_loop.analyze_full_loop`,
DESIGN section 6b), and the time response: the peak-to-peak probe depth over the last second of
the hold (below 0.5 mm the product calls the hold stable).

Usage::

    from pathlib import Path
    from haptic_collab.research.reproduce_3d import reproduce_3d
    results = reproduce_3d("all", Path("figs"))   # figs/fig10.json, fig10.png, fig11.json, ...
"""

from __future__ import annotations

import importlib
import inspect
import math
import pathlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from haptic_collab.client.devices.profiles import get_sim_profile
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.devices.trajectories import Press, hand_depth_for
from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.objects.balloon import Balloon
from haptic_collab.server.world import ContactInput, ContactOutput, World
from haptic_collab.shared.full_loop import Hand, analyze_full_loop
from haptic_collab.shared.local_model import LocalModelParams, ThresholdParams
from haptic_collab.shared.stability import eq8_stable, eq15_stable, rate_ratio
from haptic_collab.shared.types import FloatArray

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.gridspec import SubplotSpec

Figure3D = Literal["fig10", "fig11", "all"]

#: Servo rate 1/T [Hz] of the paper's experiment.
SERVO_RATE_HZ = 1000.0
#: Simulation rate 1/(N*T) [Hz] of the paper's experiment.
SIM_RATE_HZ = 20.0
#: Object stiffness at the contact of Fig. 10-11 [N/m] (the paper's 1.0 N/mm).
K_O_TARGET = 1000.0
#: How far [m] the probe is meant to press into the rest surface during the hold.
PROBE_DEPTH_M = 0.010
#: A hold whose probe depth moves less than this peak-to-peak [mm] over its last second is stable.
STABLE_HOLD_P2P_MM = 0.5
#: The simulated device (client.devices.profiles).
PROFILE = "phantom-desktop"
#: Integration threshold theta [m] of the PI cases: the client's default (``--theta-mm 1``).
THETA_M = 0.001

#: The paper's cases (section 7): (name, K_h [N/m], paper's verdict "stable").
PAPER_CASES: tuple[tuple[str, float, bool], ...] = (
    ("kh600", 600.0, True),
    ("kh700", 700.0, True),
    ("kh1200", 1200.0, False),
)


@dataclass(frozen=True)
class Timeline3D:
    """The scripted press (seconds from the first servo tick); the run ends with the hold.

    Parameters
    ----------
    standoff_m : float
        Start distance [m] of the hand outside the top.
    approach_s, press_s, hold_s : float
        Approach to the surface, press in, hold [s]. The last second of the hold is judged, so
        ``hold_s`` should be at least 1.5 s.
    """

    standoff_m: float = 0.010
    approach_s: float = 0.3
    press_s: float = 0.7
    hold_s: float = 2.5

    @property
    def hold_start_s(self) -> float:
        """When the hand target reaches its full depth [s]."""
        return self.approach_s + self.press_s

    @property
    def run_s(self) -> float:
        """Length of the run [s]: the end of the hold."""
        return self.hold_start_s + self.hold_s


@dataclass(frozen=True)
class Case3D:
    """One local model to run against the stiff balloon.

    Attributes
    ----------
    name : str
        Key in the JSON (``kh600``, ``product_p``...).
    source : {"paper", "product"}
        A gain of the paper's Fig. 10-11, or what :func:`shared.gain_design.design_gains` picks.
    mode : {"p", "pi"}
        Proportional or proportional-integral local model.
    k_h : float
        K_h [N/m].
    i_gain : float
        I [N/(m*s)] (0 for P).
    b_h : float
        Probe damper B_h [N*s/m] of the local model.
    proxy_hold : {"zoh", "foh"}
        How the servo moves the proxy between simulation ticks.
    paper_stable : bool or None
        The paper's verdict (None for the product's cases).
    """

    name: str
    source: Literal["paper", "product"]
    mode: Literal["p", "pi"]
    k_h: float
    i_gain: float = 0.0
    b_h: float = 0.0
    proxy_hold: str = "zoh"
    paper_stable: bool | None = None


@dataclass(frozen=True)
class StiffBalloon:
    """How the default balloon was stiffened for a target K_o at its top.

    Attributes
    ----------
    scale : float
        ``--stiffness-scale`` applied to every stiffness term.
    k_o_unscaled : float
        K_o [N/m] at the top of the default balloon.
    k_o : float
        K_o [N/m] at the top after scaling.
    top : (3,) float
        The top of the rest surface [m] (the anchor of the press).
    normal : (3,) float
        Outward unit normal there.
    n_vertices : int
        Mesh size.
    """

    scale: float
    k_o_unscaled: float
    k_o: float
    top: tuple[float, float, float]
    normal: tuple[float, float, float]
    n_vertices: int

    def world(self) -> World:
        """A fresh world (object at rest) with this stiffness, stepped at :data:`SIM_RATE_HZ`."""
        world: World = build_world(
            ServerOptions(sim_rate_hz=SIM_RATE_HZ, stiffness_scale=self.scale)
        )
        return world


def _top_contact(world: World) -> tuple[ContactOutput, FloatArray]:
    """The world's output for a probe 5 mm above the top of the rest surface, no force."""
    top = np.array([*world.rest_center[:2], world.rest_bounds[1, 2]])
    probe = top + np.array([0.0, 0.0, 0.005])
    out = world.tick({"probe": ContactInput(probe=probe, force=np.zeros(3))})["probe"]
    return out, top


def stiff_balloon(k_o_target: float = K_O_TARGET) -> StiffBalloon:
    """Scale the default balloon's stiffness so that K_o at its top is ``k_o_target`` [N/m].

    The scale is the target over the unscaled K_o at the top, both measured the way the server
    reports them to a client (:meth:`World.tick` with a probe just above the top).

    Raises
    ------
    ValueError
        ``k_o_target`` not a finite number > 0.
    """
    if not (math.isfinite(k_o_target) and k_o_target > 0.0):
        raise ValueError(f"k_o_target must be a finite number > 0 N/m, got {k_o_target!r}")
    plain: World = build_world(ServerOptions(sim_rate_hz=SIM_RATE_HZ))
    out0, top = _top_contact(plain)
    scale = k_o_target / out0.k_o
    stiff: World = build_world(ServerOptions(sim_rate_hz=SIM_RATE_HZ, stiffness_scale=scale))
    out1, _ = _top_contact(stiff)
    n = out1.normal
    return StiffBalloon(
        scale=float(scale),
        k_o_unscaled=float(out0.k_o),
        k_o=float(out1.k_o),
        top=(float(top[0]), float(top[1]), float(top[2])),
        normal=(float(n[0]), float(n[1]), float(n[2])),
        n_vertices=stiff.n_vertices,
    )


def combined_hand(hand: HandParams, profile: str = PROFILE) -> Hand:
    """The hand as the probe feels it: the simulated hand plus the device's mass and damping."""
    prof = get_sim_profile(profile)
    return Hand(
        mass_kg=hand.mass_kg + prof.mass_kg,
        damping_n_s_per_m=hand.damping_n_s_per_m + prof.limits.damping_n_s_per_m,
        stiffness_n_per_m=hand.stiffness_n_per_m,
    )


def _set_patch_takes_extras() -> bool:
    """Whether :meth:`ServoCore.set_patch` accepts ``b_h`` and ``proxy_hold`` (newer servo)."""
    params = inspect.signature(ServoCore.set_patch).parameters
    return "b_h" in params and "proxy_hold" in params


def _patch_kwargs(case: Case3D, n_ratio: int) -> dict[str, Any]:
    """Keyword arguments of :meth:`ServoCore.set_patch` beyond (primitive, K_h, I) for a case."""
    params = inspect.signature(ServoCore.set_patch).parameters
    out: dict[str, Any] = {}
    if "b_h" in params and "proxy_hold" in params:
        out = {"b_h": case.b_h, "proxy_hold": case.proxy_hold}
        if "hold_ticks" in params:
            out["hold_ticks"] = n_ratio  # a first-order hold spreads over one simulation period
    return out


def target_probe_depth_m(k_c: float, max_force_n: float) -> float:
    """How deep [m] the probe is pressed in against a contact stiffness ``k_c`` [N/m].

    :data:`PROBE_DEPTH_M`, or less where that would ask for more than 75 % of the device's
    ``max_force_n`` [N] in steady state (a PI model on 1000 N/m needs 10 N for 10 mm).
    """
    return min(PROBE_DEPTH_M, 0.75 * max_force_n / k_c)


@dataclass
class CaseRun:
    """The time response of one case.

    Attributes
    ----------
    case : Case3D
    t_s : (n,) float
        Servo tick times [s].
    probe_depth_m, proxy_depth_m : (n,) float
        Depth [m] of the probe and of the proxy (the local model's surface under the probe) below
        the rest top, along the inward normal.
    force_n : (n,) float
        Force magnitude [N] rendered on the user.
    sim_t_s : (m,) float
        Simulation tick times [s] (when each world tick ran).
    displacement_m : (m, n_vertices) float
        Normal displacement of every vertex after each world tick [m], outward positive.
    k_o : (m,) float
        K_o [N/m] the world reported at the contact each tick.
    vertices_rest, normals_rest : (n_vertices, 3) float
        Rest positions [m] and outward unit normals of the mesh.
    faces : (n_faces, 3) int
    hand_depth_m : float
        Hand-target depth inside the top during the hold [m].
    target_probe_depth_m : float
        Where the probe should settle [m] (:func:`target_probe_depth_m`).
    k_h_rendered : float
        K_h the servo used (after the device's stiffness clamp).
    events : dict
        Non-zero safety event counts of the servo.
    sample_tick : int
        Servo tick of each period whose state the world used (see :func:`run_case`).
    """

    case: Case3D
    t_s: FloatArray
    probe_depth_m: FloatArray
    proxy_depth_m: FloatArray
    force_n: FloatArray
    sim_t_s: FloatArray
    displacement_m: FloatArray
    k_o: FloatArray
    vertices_rest: FloatArray
    normals_rest: FloatArray
    faces: NDArray[np.int32]
    hand_depth_m: float
    target_probe_depth_m: float
    k_h_rendered: float
    events: dict[str, int]
    sample_tick: int


def run_case(
    stiff: StiffBalloon,
    case: Case3D,
    timeline: Timeline3D | None = None,
    hand: HandParams | None = None,
    sample_tick: int = 0,
) -> CaseRun:
    """Run one case: servo at 1 kHz, world at 20 Hz, one user pressing the top.

    The user's state (probe and rendered force) is taken after servo tick ``sample_tick`` of
    each simulation period, as a client sending its state once per period would; the world
    tick at the end of the period uses that latest state (Step 3) and its new local model is
    applied from the first servo tick of the next period. ``sample_tick = 0`` is the paper's
    decimator (the force of the first servo tick of the period, a whole period of computation);
    ``N - 1`` the freshest force.

    The hand target goes ``hand_depth_for(target_probe_depth_m(k_c, F_max), k_c)`` inside the
    top, ``k_c`` the contact stiffness the probe meets in steady state (K_h in series with K_o for
    P, K_o for PI), so that the probe settles about 10 mm in (less if that force is more than
    the device can hold). The device's stiffness limit is raised to the case's
    K_h when that is above it (the paper ran 1.2 N/mm on its Phantom; the profile's limit is
    the product's own safety margin, not what this experiment is about).

    Raises
    ------
    ValueError
        Bad gains (see :meth:`ServoCore.set_patch`), ``sample_tick`` outside [0, N), or a case
        with a probe damper or a first-order proxy hold on a servo that does not take them yet.
    """
    tl = timeline if timeline is not None else Timeline3D()
    hand = hand if hand is not None else HandParams()
    n_ratio = rate_ratio(SERVO_RATE_HZ, SIM_RATE_HZ)
    if not 0 <= sample_tick < n_ratio:
        raise ValueError(f"sample_tick must be in [0, {n_ratio}), got {sample_tick!r}")
    extras = _set_patch_takes_extras()
    if not extras and (case.b_h != 0.0 or case.proxy_hold != "zoh"):
        raise ValueError(
            f"case {case.name}: ServoCore.set_patch does not take b_h/proxy_hold yet "
            f"(b_h = {case.b_h:g}, proxy_hold = {case.proxy_hold})"
        )
    servo_period = 1.0 / SERVO_RATE_HZ
    world = stiff.world()
    obj = world.obj
    anchor = np.asarray(stiff.top, dtype=np.float64)
    normal = np.asarray(stiff.normal, dtype=np.float64)
    prof = get_sim_profile(PROFILE)
    k_c = stiff.k_o if case.i_gain > 0.0 else case.k_h * stiff.k_o / (case.k_h + stiff.k_o)
    probe_depth = target_probe_depth_m(k_c, prof.limits.max_force_n)
    depth = hand_depth_for(probe_depth, k_c, hand.stiffness_n_per_m)
    press = Press(
        stiff.top,
        stiff.normal,
        standoff_m=tl.standoff_m,
        depth_m=depth,
        delay_s=0.0,
        approach_s=tl.approach_s,
        press_s=tl.press_s,
        hold_s=tl.hold_s,
        release_s=1.0,
    )
    # the paper's experiment: no motor-heating limit (client/thermal.py) on its presses
    limits = replace(prof.limits, max_continuous_force_n=None)
    if case.k_h > limits.max_stiffness_n_per_m:
        limits = replace(limits, max_stiffness_n_per_m=case.k_h)
    device = SimDevice(
        prof, press, hand, limits=limits.centered_at(stiff.top), servo_period_s=servo_period
    )
    n_ticks = round(tl.run_s * SERVO_RATE_HZ)
    lm = LocalModelParams(
        k_h=case.k_h,
        i_gain=case.i_gain,
        servo_period_s=servo_period,
        threshold=ThresholdParams(mode="fixed", theta_m=THETA_M),
        release_time_s=2.0 / SIM_RATE_HZ,
        integral_limit_n=limits.max_force_n,
    )
    recorder = TelemetryRecorder(capacity=n_ticks + 16)
    core = ServoCore(
        device, ServoConfig(servo_rate_hz=SERVO_RATE_HZ), local_model=lm, recorder=recorder
    )
    set_patch: Callable[..., Any] = core.set_patch
    patch_kwargs = _patch_kwargs(case, n_ratio)
    device.open()
    core.enable_forces()
    state = ContactInput(probe=np.asarray(press(0.0), dtype=np.float64), force=np.zeros(3))
    sim_t: list[float] = []
    disp: list[FloatArray] = []
    k_o: list[float] = []
    rest = np.asarray(obj.rest_vertices, dtype=np.float64)
    normals_rest = (
        obj.rest_normals if isinstance(obj, Balloon) else _vertex_normals(rest, world.faces)
    )
    for n in range(n_ticks):
        if n % n_ratio == 0:
            # one simulation tick, as server.room.Room.tick: the user's latest state
            out = world.tick({"user": state})["user"]
            set_patch(out.primitive, case.k_h, case.i_gain, **patch_kwargs)
            sim_t.append(n * servo_period)
            k_o.append(float(out.k_o))
            disp.append(np.einsum("ij,ij->i", world.vertices - rest, normals_rest))
        core.tick(n * servo_period)
        if n % n_ratio == sample_tick:
            # the client's state message for this period (probe and force rendered on the user)
            snap = core.latest()
            if snap is not None:
                state = ContactInput(
                    probe=np.asarray(snap.probe_m, dtype=np.float64),
                    force=np.asarray(snap.force_n, dtype=np.float64),
                )
    rows = recorder.rows()
    cols = {name: i for i, name in enumerate(recorder.columns)}
    probe = rows[:, [cols["probe_x_m"], cols["probe_y_m"], cols["probe_z_m"]]]
    proxy = rows[:, [cols["proxy_x_m"], cols["proxy_y_m"], cols["proxy_z_m"]]]
    status = core.status()
    snap = core.latest()
    return CaseRun(
        case=case,
        t_s=rows[:, cols["t_s"]],
        probe_depth_m=(anchor - probe) @ normal,
        proxy_depth_m=(anchor - proxy) @ normal,
        force_n=rows[:, cols["force_n"]],
        sim_t_s=np.asarray(sim_t),
        displacement_m=np.asarray(disp),
        k_o=np.asarray(k_o),
        vertices_rest=rest,
        normals_rest=np.asarray(normals_rest, dtype=np.float64),
        faces=np.asarray(world.faces),
        hand_depth_m=float(depth),
        target_probe_depth_m=float(probe_depth),
        k_h_rendered=float(snap.k_h) if snap is not None else case.k_h,
        events={k: v for k, v in status.counts.items() if v},
        sample_tick=sample_tick,
    )


def _vertex_normals(vertices: FloatArray, faces: NDArray[np.int32]) -> FloatArray:
    """Area-weighted outward vertex normals (n, 3) of a closed mesh."""
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(vertices[f[:, 1]] - vertices[f[:, 0]], vertices[f[:, 2]] - vertices[f[:, 0]])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-18)


def case_result(
    run: CaseRun, timeline: Timeline3D, hand: HandParams, k_o_top: float
) -> dict[str, Any]:
    """The JSON object of one case (SI units, plus the ``_mm`` figures of merit).

    ``steady_state_error_mm`` is the probe minus proxy depth, mean over the last 0.5 s;
    ``hold_p2p_mm`` the peak-to-peak probe depth over the last second of the hold.
    """
    c = run.case
    t_end = timeline.run_s
    last1 = run.t_s >= t_end - 1.0 - 1e-9
    last05 = run.t_s >= t_end - 0.5 - 1e-9
    hold_sim = run.sim_t_s >= timeline.hold_start_s - 1e-9
    err = run.probe_depth_m - run.proxy_depth_m
    p2p_mm = float(np.ptp(run.probe_depth_m[last1]) * 1000.0)
    k_o = float(np.mean(run.k_o[hold_sim])) if np.any(hold_sim) else k_o_top
    felt = combined_hand(hand)
    loop: dict[str, Any] = {
        "k_o": k_o,
        "k_h": run.k_h_rendered,
        "i_gain": c.i_gain,
        "b_h": c.b_h,
        "servo_rate_hz": SERVO_RATE_HZ,
        "sim_rate_hz": SIM_RATE_HZ,
        "proxy_hold": c.proxy_hold,
    }
    full = analyze_full_loop(felt, **loop)  # worst sampling tick: the product's criterion
    by_tick = [
        analyze_full_loop(felt, sample_tick=j, **loop).spectral_radius
        for j in range(rate_ratio(SERVO_RATE_HZ, SIM_RATE_HZ))
    ]
    if c.i_gain > 0.0:
        nti = c.i_gain * rate_ratio(SERVO_RATE_HZ, SIM_RATE_HZ) / SERVO_RATE_HZ
        sim_stable, condition = eq15_stable(run.k_h_rendered, k_o, nti), "eq. 15"
    else:
        sim_stable, condition = eq8_stable(run.k_h_rendered, k_o), "eq. 8"
    return {
        "source": c.source,
        "mode": c.mode,
        "k_h_n_per_m": run.k_h_rendered,
        "i_gain_n_per_m_s": c.i_gain,
        "b_h_n_s_per_m": c.b_h,
        "proxy_hold": c.proxy_hold,
        "k_o_n_per_m": k_o,
        "steady_state_error_mm": float(np.mean(err[last05]) * 1000.0),
        "probe_depth_mm": float(np.mean(run.probe_depth_m[last05]) * 1000.0),
        "proxy_depth_mm": float(np.mean(run.proxy_depth_m[last05]) * 1000.0),
        "force_n": float(np.mean(run.force_n[last05])),
        "max_force_n": float(np.max(run.force_n)),
        "hold_p2p_mm": p2p_mm,
        "hold_stable": p2p_mm < STABLE_HOLD_P2P_MM,
        "sim_loop_stable": bool(sim_stable),
        "sim_loop_condition": condition,
        "full_loop_stable": bool(full.stable),
        "full_loop_spectral_radius": float(full.spectral_radius),
        "full_loop_worst_sample_tick": int(full.worst_sample_tick),
        "sample_tick": run.sample_tick,
        "full_loop_spectral_radius_at_sample_tick": float(by_tick[run.sample_tick]),
        "full_loop_unstable_sample_ticks": [j for j, r in enumerate(by_tick) if r >= 1.0],
        "paper_stable": c.paper_stable,
        "hand_depth_mm": run.hand_depth_m * 1000.0,
        "target_probe_depth_mm": run.target_probe_depth_m * 1000.0,
        "servo_events": run.events,
        "hand": _hand_json(hand),
    }


def _hand_json(hand: HandParams) -> dict[str, Any]:
    prof = get_sim_profile(PROFILE)
    return {
        "mass_kg": hand.mass_kg,
        "stiffness_n_per_m": hand.stiffness_n_per_m,
        "damping_n_s_per_m": hand.damping_n_s_per_m,
        "device": {
            "profile": PROFILE,
            "mass_kg": prof.mass_kg,
            "damping_n_s_per_m": prof.limits.damping_n_s_per_m,
        },
        "as_felt_by_the_probe": combined_hand(hand).as_dict(),
    }


# --------------------------------------------------------------------------------------------
# the product's own gains (shared.gain_design, when present)
# --------------------------------------------------------------------------------------------


def product_cases(k_o: float) -> tuple[list[Case3D], list[str]]:
    """The gains the product's design picks for ``k_o`` [N/m], modes P and PI.

    Uses ``shared.gain_design.design_gains`` when it exists (no delay, the device's stiffness
    and damping limits as ``k_h_max`` and ``b_h_max`` as the client passes them, the design's
    other defaults). Returns the cases and notes on anything
    skipped (a missing design module, a servo without the probe damper or the first-order hold).
    """
    try:
        design = importlib.import_module("haptic_collab.shared.gain_design").design_gains
    except (ImportError, AttributeError):
        return [], ["shared.gain_design.design_gains is not available: product cases skipped"]
    limits = get_sim_profile(PROFILE).limits
    k_h_max = limits.max_stiffness_n_per_m
    # as client.app does: the probe damper is bounded by what the device can render
    b_h_max = min(1e3, float(getattr(limits, "max_damping_n_s_per_m", 0.0)))
    extras = _set_patch_takes_extras()
    cases: list[Case3D] = []
    notes: list[str] = []
    for mode in ("p", "pi"):
        try:
            g = design(
                k_o,
                b_o=0.0,
                servo_rate_hz=SERVO_RATE_HZ,
                sim_rate_hz=SIM_RATE_HZ,
                delay_ticks=0,
                mode=mode,
                k_h_max=k_h_max,
                **({"b_h_max": b_h_max} if b_h_max > 0.0 else {}),
            )
        except (TypeError, ValueError) as exc:
            notes.append(f"design_gains(mode={mode!r}) failed, case skipped: {exc}")
            continue
        case = Case3D(
            name=f"product_{mode}",
            source="product",
            mode=mode,  # type: ignore[arg-type]
            k_h=float(g.k_h),
            i_gain=float(getattr(g, "i_gain", 0.0)),
            b_h=float(getattr(g, "b_h", 0.0)),
            proxy_hold=str(getattr(g, "proxy_hold", "zoh")),
        )
        if not extras and (case.b_h != 0.0 or case.proxy_hold != "zoh"):
            notes.append(
                f"product_{mode} (K_h = {case.k_h:g}, B_h = {case.b_h:g}, "
                f"{case.proxy_hold}) skipped: ServoCore.set_patch takes no b_h/proxy_hold yet"
            )
            continue
        cases.append(case)
    return cases, notes


# --------------------------------------------------------------------------------------------
# notes
# --------------------------------------------------------------------------------------------


def _tick_ranges(ticks: Sequence[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"``."""
    out: list[str] = []
    for j in ticks:
        if out and out[-1].split("-")[-1] == str(j - 1):
            out[-1] = f"{out[-1].split('-')[0]}-{j}"
        else:
            out.append(str(j))
    return ", ".join(out)


def _paper_note(
    cases: dict[str, dict[str, Any]],
    hand: HandParams,
    phase_check: dict[str, dict[str, Any]] | None = None,
) -> str:
    """Where our verdicts disagree with the paper's experiment, written from the measured numbers."""
    felt = combined_hand(hand)
    paper = [(name, c) for name, c in cases.items() if c.get("paper_stable") is not None]
    if not paper:
        return ""

    def kh(c: dict[str, Any]) -> str:
        return f"K_h = {c['k_h_n_per_m']:g}"

    def agreement(key: str) -> str:
        bad = [kh(c) for _, c in paper if c[key] != c["paper_stable"]]
        return (
            "agrees with the paper" if not bad else f"DISAGREES with the paper for {', '.join(bad)}"
        )

    j = paper[0][1]["sample_tick"]
    parts = [
        "Paper (Phantom Desktop, K_o = 1.0 N/mm): K_h = 0.6 and 0.7 N/mm stable, 1.2 N/mm unstable.",
        f"Simulation loop (eq. 8, probe as a position source): {agreement('sim_loop_stable')}.",
        f"Time runs (the world takes the force of servo tick {j} of each period, the paper's "
        "decimator), hold p2p over the last second: "
        + ", ".join(
            f"{kh(c)}: {c['hold_p2p_mm']:.2f} mm (full-loop rho "
            f"{c['full_loop_spectral_radius_at_sample_tick']:.2f} at that tick)"
            for _, c in paper
        )
        + f"; {agreement('hold_stable')}.",
        f"Full loop with our default simulated hand ({felt.mass_kg:g} kg, "
        f"{felt.damping_n_s_per_m:g} N*s/m, {felt.stiffness_n_per_m:g} N/m as the probe feels "
        "it), worst sampling tick (the product's criterion): "
        + ", ".join(
            f"{kh(c)}: {'stable' if c['full_loop_stable'] else 'unstable'} "
            f"(rho {c['full_loop_spectral_radius']:.3f}"
            + (
                f", unstable for ticks {_tick_ranges(c['full_loop_unstable_sample_ticks'])})"
                if c["full_loop_unstable_sample_ticks"]
                else ")"
            )
            for _, c in paper
        )
        + f"; {agreement('full_loop_stable')}.",
    ]
    if phase_check:
        parts.append(
            "Run again with the world taking the force of the worst tick: "
            + ", ".join(
                f"K_h = {p['k_h_n_per_m']:g} at tick {p['sample_tick']}: hold p2p "
                f"{p['hold_p2p_mm']:.2f} mm ({'stable' if p['hold_stable'] else 'oscillates'})"
                for p in phase_check.values()
            )
            + "."
        )
    if any(c["full_loop_stable"] != c["paper_stable"] for _, c in paper):
        parts.append(
            "The paper's analysis holds the probe as a position source; a hand holding the device "
            "closes a second loop through the local model that the 20 Hz proxy jumps excite "
            "(DESIGN section 6b), and which sampling tick the simulation sees decides whether it "
            "grows. The paper's real hand, Phantom and timing are not ours; nothing was tuned to "
            "match."
        )
    return " ".join(parts)


# --------------------------------------------------------------------------------------------
# plots (matplotlib's object API: no pyplot, no global backend)
# --------------------------------------------------------------------------------------------

_DPI = 110
_CMAP = "coolwarm"
#: Half-width [m] of the cross-section drawn around the top.
_SECTION_HALF_M = 0.06


def _new_figure(width_in: float, height_in: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _surface(run: CaseRun, frame: int) -> FloatArray:
    """Vertex positions (n, 3) [m] after world tick ``frame``."""
    w = run.displacement_m[frame]
    return run.vertices_rest + w[:, None] * run.normals_rest


def _probe_depth_at(run: CaseRun, frame: int) -> float:
    """Probe depth [m] at the servo tick of world tick ``frame``."""
    i = min(int(np.searchsorted(run.t_s, run.sim_t_s[frame])), len(run.t_s) - 1)
    return float(run.probe_depth_m[i])


def _mesh_panel(
    fig: Figure, spec: SubplotSpec, run: CaseRun, frame: int, norm: Any, title: str
) -> Axes:
    """3-D view of the balloon after world tick ``frame``, faces coloured by displacement."""
    from matplotlib import colormaps
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    ax = fig.add_subplot(spec, projection="3d")
    verts = _surface(run, frame)
    f = np.asarray(run.faces, dtype=np.int64)
    tri = verts[f]
    face_w_mm = run.displacement_m[frame][f].mean(axis=1) * 1000.0
    rgba = colormaps[_CMAP](norm(face_w_mm))
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-18)
    light = np.array([-0.4, -0.5, 0.77])
    shade = 0.6 + 0.4 * np.clip(fn @ (light / np.linalg.norm(light)), 0.0, 1.0)
    rgba[:, :3] *= shade[:, None]
    ax.add_collection3d(Poly3DCollection(tri, facecolors=rgba, edgecolors="none"))
    top = float(run.vertices_rest[:, 2].max())
    tip = top - _probe_depth_at(run, frame)
    ax.plot([0.0, 0.0], [0.0, 0.0], [tip, top + 0.05], color="k", lw=2.0)
    r = float(np.max(np.abs(run.vertices_rest)))
    ax.set_xlim(-r, r)
    ax.set_ylim(-r, r)
    ax.set_zlim(-r, r + 0.03)
    ax.set_box_aspect((1.0, 1.0, (2 * r + 0.03) / (2 * r)), zoom=1.25)
    ax.view_init(elev=18.0, azim=-60.0)
    ax.set_axis_off()
    ax.set_title(title, fontsize=10)
    return ax


def _section(
    vertices: FloatArray, faces: NDArray[np.int32], values: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The mesh cut by the plane y = 0.

    Parameters
    ----------
    vertices : (n, 3) float [m]
    faces : (m, 3) int
    values : (n,) float
        A per-vertex quantity, interpolated linearly along the cut.

    Returns
    -------
    segments : (k, 2, 2) float [m]
        (x, z) end points of each piece of the cut.
    segment_values : (k, 2) float
        ``values`` at those end points.
    """
    f = np.asarray(faces, dtype=np.int64)
    y = vertices[:, 1] + 1e-12  # vertices exactly on the plane count as just above it
    tri_y = y[f]
    crossing = (tri_y.min(axis=1) < 0.0) & (tri_y.max(axis=1) > 0.0)
    segs: list[list[tuple[float, float]]] = []
    vals: list[list[float]] = []
    for face in f[crossing]:
        pts: list[tuple[float, float]] = []
        vs: list[float] = []
        for a, b in ((face[0], face[1]), (face[1], face[2]), (face[2], face[0])):
            ya, yb = y[a], y[b]
            if (ya < 0.0) != (yb < 0.0):
                t = ya / (ya - yb)
                p = vertices[a] + t * (vertices[b] - vertices[a])
                pts.append((float(p[0]), float(p[2])))
                vs.append(float(values[a] + t * (values[b] - values[a])))
        if len(pts) == 2:
            segs.append(pts)
            vals.append(vs)
    return np.asarray(segs, dtype=np.float64).reshape(-1, 2, 2), np.asarray(vals).reshape(-1, 2)


def _section_panel(ax: Axes, run: CaseRun, frame: int, norm: Any) -> None:
    """The surface cut by y = 0 near the top after world tick ``frame``: rest, deformed, probe."""
    from matplotlib import colormaps
    from matplotlib.collections import LineCollection

    top = float(run.vertices_rest[:, 2].max())
    h = _SECTION_HALF_M
    w = run.displacement_m[frame]
    for verts, deformed in ((run.vertices_rest, False), (_surface(run, frame), True)):
        seg, val = _section(verts, run.faces, w)
        keep = (np.abs(seg[:, :, 0]) <= h).all(axis=1) & (seg[:, :, 1] > 0.0).all(axis=1)
        seg, val = seg[keep], val[keep]
        mm = list(np.stack([seg[:, :, 0], seg[:, :, 1] - top], axis=-1) * 1000.0)
        if deformed:  # coloured by the normal displacement, as the 3-D view
            colors = colormaps[_CMAP](norm(val.mean(axis=1) * 1000.0))
            ax.add_collection(LineCollection(mm, colors=colors, linewidths=2.4))
        else:
            ax.add_collection(LineCollection(mm, colors="0.6", linestyles="--", linewidths=1.0))
    depth_mm = _probe_depth_at(run, frame) * 1000.0
    ax.plot([0.0], [-depth_mm], "o", color="k", ms=5, label="probe")
    i = min(int(np.searchsorted(run.t_s, run.sim_t_s[frame])), len(run.t_s) - 1)
    proxy_mm = run.proxy_depth_m[i] * 1000.0
    ax.plot([-15.0, 15.0], [-proxy_mm, -proxy_mm], color="tab:red", lw=1.2, label="local model")
    ax.set_xlim(-h * 1000.0, h * 1000.0)
    ax.set_ylim(-20.0, 3.0)
    ax.set_xlabel("x [mm] (section y = 0)", fontsize=9)
    ax.set_ylabel("z - top [mm]", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower center", fontsize=7.5, ncols=2)


def _colorbar(fig: Figure, axes: Any, norm: Any) -> None:
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable

    sm = ScalarMappable(norm=norm, cmap=colormaps[_CMAP])
    cb = fig.colorbar(sm, ax=axes, shrink=0.8, pad=0.01)
    lo, hi = float(norm.vmin), float(norm.vmax)
    cb.set_ticks([lo, lo / 2.0, 0.0, hi / 2.0, hi])
    cb.ax.yaxis.set_major_formatter("{x:.1f}")
    cb.set_label("normal displacement [mm]\n(dent < 0 < bulge)", fontsize=9)


def _depth_panel(
    ax: Axes,
    run: CaseRun,
    res: dict[str, Any],
    timeline: Timeline3D,
    worst: CaseRun | None = None,
) -> None:
    if worst is not None:
        ax.plot(
            worst.t_s,
            worst.probe_depth_m * 1000.0,
            color="0.55",
            lw=0.9,
            label=f"probe, world takes tick {worst.sample_tick}",
        )
    ax.plot(run.t_s, run.probe_depth_m * 1000.0, color="tab:blue", lw=1.5, label="probe $x_h$")
    ax.plot(run.t_s, run.proxy_depth_m * 1000.0, color="tab:red", lw=1.5, label="proxy $x_o$")
    ax.axvspan(timeline.run_s - 1.0, timeline.run_s, color="0.92", zorder=0)
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("depth below the rest top [mm]")
    ax.grid(True, alpha=0.3)
    ax.set_xlim(0.0, timeline.run_s)
    sim = "stable" if res["sim_loop_stable"] else "UNSTABLE"
    full = "stable" if res["full_loop_stable"] else "UNSTABLE"
    ax.set_title(
        f"hold p2p {res['hold_p2p_mm']:.2f} mm, error {res['steady_state_error_mm']:.2f} mm\n"
        f"{res['sim_loop_condition']}: {sim}; full loop: {full} "
        f"(rho {res['full_loop_spectral_radius']:.2f})",
        fontsize=9,
    )
    ax.legend(loc="lower right", fontsize=7.5)


def _case_title(c: Case3D) -> str:
    if c.source == "paper":
        return f"P, K_h = {c.k_h / 1000.0:g} N/mm (paper)"
    extra = f", I = {c.i_gain:.0f}" if c.i_gain > 0.0 else ""
    damper = f", B_h = {c.b_h:g}" if c.b_h > 0.0 else ""
    return f"product {c.mode.upper()}: K_h = {c.k_h:.0f} N/m{extra}{damper}, {c.proxy_hold}"


def _norm(displacements_m: Sequence[FloatArray]) -> Any:
    """Colour scale: the deepest dent to the largest bulge [mm], centred on 0."""
    from matplotlib.colors import TwoSlopeNorm

    w = np.concatenate([np.ravel(d) for d in displacements_m]) * 1000.0
    return TwoSlopeNorm(
        vmin=min(float(w.min()), -1e-3), vcenter=0.0, vmax=max(float(w.max()), 1e-3)
    )


def _plot_fig10(
    path: pathlib.Path,
    runs: list[CaseRun],
    results: dict[str, dict[str, Any]],
    tl: Timeline3D,
    worst: dict[str, CaseRun],
) -> None:
    ncol = len(runs)
    fig = _new_figure(4.4 * ncol + 1.2, 11.0)
    gs = fig.add_gridspec(3, ncol, height_ratios=[1.2, 0.55, 1.0])
    norm = _norm([r.displacement_m[-1] for r in runs])
    meshes = []
    for j, run in enumerate(runs):
        last = len(run.sim_t_s) - 1
        meshes.append(_mesh_panel(fig, gs[0, j], run, last, norm, _case_title(run.case)))
        _section_panel(fig.add_subplot(gs[1, j]), run, last, norm)
        _depth_panel(
            fig.add_subplot(gs[2, j]), run, results[run.case.name], tl, worst.get(run.case.name)
        )
    _colorbar(fig, meshes, norm)
    k_o = results[runs[0].case.name]["k_o_n_per_m"]
    fig.suptitle(
        f"Fig. 10: local models on the water balloon with K_o = {k_o:.0f} N/m at the top; surface "
        "at the end of the hold (the last second, shaded, is judged)",
        fontsize=11,
    )
    fig.savefig(path)


def _fig11_frames(run: CaseRun, tl: Timeline3D, count: int = 4) -> list[int]:
    """``count`` consecutive world ticks of the judged last second, from the deepest surface."""
    last = np.flatnonzero(run.sim_t_s >= tl.run_s - 1.0 - 1e-9)
    if len(last) == 0:
        last = np.arange(len(run.sim_t_s))
    k = int(last[int(np.argmin(run.displacement_m[last].min(axis=1)))])
    first = max(0, min(k, len(run.sim_t_s) - count))
    return list(range(first, min(first + count, len(run.sim_t_s))))


def _plot_fig11(
    path: pathlib.Path, run: CaseRun, res: dict[str, Any], tl: Timeline3D
) -> list[float]:
    frames = _fig11_frames(run, tl)
    fig = _new_figure(17.0, 10.5)
    gs = fig.add_gridspec(3, len(frames), height_ratios=[1.1, 0.55, 0.9])
    norm = _norm([run.displacement_m[frames]])
    meshes = []
    for j, k in enumerate(frames):
        title = f"t = {run.sim_t_s[k]:.2f} s (world tick {k})"
        meshes.append(_mesh_panel(fig, gs[0, j], run, k, norm, title))
        _section_panel(fig.add_subplot(gs[1, j]), run, k, norm)
    _colorbar(fig, meshes, norm)
    ax = fig.add_subplot(gs[2, :])
    _depth_panel(ax, run, res, tl)
    for k in frames:
        ax.axvline(run.sim_t_s[k], color="k", lw=0.8, ls=":")
    fig.suptitle(
        f"Fig. 11: K_h = {run.case.k_h / 1000.0:g} N/mm > K_o = {res['k_o_n_per_m'] / 1000.0:.2f} "
        "N/mm violates eq. 8: consecutive world ticks of the surface (dotted lines below)",
        fontsize=11,
    )
    fig.savefig(path)
    return [float(run.sim_t_s[k]) for k in frames]


# --------------------------------------------------------------------------------------------
# figures
# --------------------------------------------------------------------------------------------


def _common(stiff: StiffBalloon, tl: Timeline3D, hand: HandParams) -> dict[str, Any]:
    return {
        "object": {
            "mesh": "default water balloon (server.objects.balloon, icosphere r = 0.1 m)",
            "n_vertices": stiff.n_vertices,
            "stiffness_scale": stiff.scale,
            "k_o_unscaled_top_n_per_m": stiff.k_o_unscaled,
            "k_o_top_n_per_m": stiff.k_o,
        },
        "servo_rate_hz": SERVO_RATE_HZ,
        "sim_rate_hz": SIM_RATE_HZ,
        "delay_ticks": 0,
        "device_profile": PROFILE,
        "hand": _hand_json(hand),
        "timeline_s": {
            "approach": tl.approach_s,
            "press": tl.press_s,
            "hold": tl.hold_s,
            "hold_start": tl.hold_start_s,
            "end": tl.run_s,
            "standoff_m": tl.standoff_m,
        },
        "target_probe_depth_m": PROBE_DEPTH_M,
        "stable_hold_p2p_mm": STABLE_HOLD_P2P_MM,
    }


def _paper_case(name: str) -> Case3D:
    for n, k_h, stable in PAPER_CASES:
        if n == name:
            return Case3D(name=n, source="paper", mode="p", k_h=k_h, paper_stable=stable)
    raise KeyError(name)


def _cap_note() -> str:
    cap = get_sim_profile(PROFILE).limits.max_stiffness_n_per_m
    return (
        f"The {PROFILE} profile limits K_h to {cap:g} N/m; for the paper's gains above it the "
        "limit is raised to the gain (the paper ran 1.2 N/mm on its Phantom)."
    )


def _run_all(
    stiff: StiffBalloon,
    cases: Sequence[Case3D],
    tl: Timeline3D,
    hand: HandParams,
    sample_tick: int,
) -> tuple[list[CaseRun], dict[str, dict[str, Any]]]:
    runs = [run_case(stiff, c, tl, hand, sample_tick) for c in cases]
    results = {r.case.name: case_result(r, tl, hand, stiff.k_o) for r in runs}
    return runs, results


def _phase_check(
    stiff: StiffBalloon,
    runs: Sequence[CaseRun],
    results: dict[str, dict[str, Any]],
    tl: Timeline3D,
    hand: HandParams,
) -> tuple[dict[str, CaseRun], dict[str, dict[str, Any]]]:
    """Re-run each paper case whose full loop is unstable at the worst tick, at that tick."""
    worst_runs: dict[str, CaseRun] = {}
    check: dict[str, dict[str, Any]] = {}
    for run in runs:
        res = results[run.case.name]
        j = res["full_loop_worst_sample_tick"]
        if run.case.source != "paper" or res["full_loop_stable"] or j == run.sample_tick:
            continue
        again = run_case(stiff, run.case, tl, hand, sample_tick=j)
        r2 = case_result(again, tl, hand, stiff.k_o)
        worst_runs[run.case.name] = again
        check[run.case.name] = {
            "k_h_n_per_m": r2["k_h_n_per_m"],
            "sample_tick": j,
            "full_loop_spectral_radius_at_sample_tick": r2[
                "full_loop_spectral_radius_at_sample_tick"
            ],
            "hold_p2p_mm": r2["hold_p2p_mm"],
            "hold_stable": r2["hold_stable"],
            "steady_state_error_mm": r2["steady_state_error_mm"],
        }
    return worst_runs, check


def fig10(
    out_dir: pathlib.Path,
    *,
    stiff: StiffBalloon | None = None,
    timeline: Timeline3D | None = None,
    hand: HandParams | None = None,
    product: bool = True,
    sample_tick: int = 0,
) -> dict[str, Any]:
    """Fig. 10: K_h = 600 and 700 N/m (P) on K_o = 1000 N/m, plus the product's own gains.

    Writes ``fig10.png`` into ``out_dir`` and returns the JSON object: per case (``cases``) the
    figures of merit of :func:`case_result`; ``worst_phase`` the paper cases re-run with the world
    taking the force of the full loop's worst sampling tick; ``note`` where our verdicts disagree
    with the paper's; ``notes`` the rest (the device's stiffness limit, product cases skipped).
    """
    tl = timeline if timeline is not None else Timeline3D()
    hand = hand if hand is not None else HandParams()
    stiff = stiff if stiff is not None else stiff_balloon()
    cases = [_paper_case("kh600"), _paper_case("kh700")]
    notes: list[str] = []
    if product:
        extra, notes = product_cases(stiff.k_o)
        cases += extra
    runs, results = _run_all(stiff, cases, tl, hand, sample_tick)
    worst_runs, check = _phase_check(stiff, runs, results, tl, hand)
    _plot_fig10(out_dir / "fig10.png", runs, results, tl, worst_runs)
    out = _common(stiff, tl, hand)
    out["cases"] = results
    out["worst_phase"] = check
    out["note"] = _paper_note(results, hand, check)
    out["notes"] = [_cap_note(), *notes]
    if any(c.source == "product" for c in cases):
        out["notes"].append(
            "The product's gains run on the same servo as the paper's (fixed theta = "
            f"{THETA_M * 1000.0:g} mm, no passivity layer), not with every client.app setting."
        )
    return out


def fig11(
    out_dir: pathlib.Path,
    *,
    stiff: StiffBalloon | None = None,
    timeline: Timeline3D | None = None,
    hand: HandParams | None = None,
    sample_tick: int = 0,
) -> dict[str, Any]:
    """Fig. 11: K_h = 1200 N/m (P) on K_o = 1000 N/m violates eq. 8.

    Writes ``fig11.png`` (consecutive world ticks of the surface and the depth trace) and returns
    the JSON object, as :func:`fig10`.
    """
    tl = timeline if timeline is not None else Timeline3D()
    hand = hand if hand is not None else HandParams()
    stiff = stiff if stiff is not None else stiff_balloon()
    runs, results = _run_all(stiff, [_paper_case("kh1200")], tl, hand, sample_tick)
    frames = _plot_fig11(out_dir / "fig11.png", runs[0], results["kh1200"], tl)
    out = _common(stiff, tl, hand)
    out["cases"] = results
    out["frames_t_s"] = frames
    out["note"] = _paper_note(results, hand)
    out["notes"] = [_cap_note()]
    return out


def reproduce_3d(
    figure: Figure3D,
    out_dir: pathlib.Path,
    *,
    timeline: Timeline3D | None = None,
    hand: HandParams | None = None,
    product: bool = True,
    sample_tick: int = 0,
) -> dict[str, dict[str, Any]]:
    """Recompute the paper's Fig. 10 and/or 11 and write ``<fig>.json`` and ``<fig>.png``.

    Parameters
    ----------
    figure : {"fig10", "fig11", "all"}
    out_dir : pathlib.Path
        Output directory, created if missing.
    timeline : Timeline3D, optional
        The press (default: 0.3 s approach, 0.7 s press, 2.5 s hold).
    hand : HandParams, optional
        The simulated hand (default :class:`HandParams`).
    product : bool
        Also run the product's own gains (Fig. 10), when ``shared.gain_design`` exists.
    sample_tick : int
        Servo tick of each period whose force the world takes (default 0, the paper's
        decimator; see :func:`run_case`).

    Returns
    -------
    dict
        The JSON objects written, keyed by figure name. With both figures, each ``note``
        covers all three of the paper's gains.

    Raises
    ------
    ValueError
        Unknown figure name.
    """
    import json

    if figure not in ("fig10", "fig11", "all"):
        raise ValueError(f"figure must be one of fig10, fig11, all; got {figure!r}")
    hand = hand if hand is not None else HandParams()
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stiff = stiff_balloon()
    results: dict[str, dict[str, Any]] = {}
    if figure in ("fig10", "all"):
        results["fig10"] = fig10(
            out_dir,
            stiff=stiff,
            timeline=timeline,
            hand=hand,
            product=product,
            sample_tick=sample_tick,
        )
    if figure in ("fig11", "all"):
        results["fig11"] = fig11(
            out_dir, stiff=stiff, timeline=timeline, hand=hand, sample_tick=sample_tick
        )
    if len(results) == 2:  # one note over the paper's three gains
        note = _paper_note(
            {**results["fig10"]["cases"], **results["fig11"]["cases"]},
            hand,
            results["fig10"]["worst_phase"],
        )
        for data in results.values():
            data["note"] = note
    for name, data in results.items():
        with open(out_dir / f"{name}.json", "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=2, allow_nan=False)
            fh.write("\n")
    return results
