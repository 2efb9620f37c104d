"""One press of Fig. 10-11: a local model's case run on the stiffened balloon, and its judgement.

The paper's section 7 on the product's own code (:mod:`haptic_collab.research.harness_3d`, every
block in-process, tick by tick, integer ticks and no clock or network):

- the object: the server's :class:`server.world.World` around the default water balloon with
  ``--stiffness-scale`` chosen so that K_o at the top is 1000 N/m (the scale is computed from the
  unscaled K_o at the top: :func:`stiff_balloon`), stepped at 20 Hz;
- the user: :class:`client.devices.sim.SimDevice` with the default :class:`HandParams` on the
  ``phantom-desktop`` profile, its hand following a :class:`client.devices.trajectories.Press`
  that approaches the top and presses the probe about 10 mm in, then holds;
- the haptic loop: :class:`client.servo.ServoCore` ticked at 1 kHz with an injected time.

Every simulation tick (50 servo ticks), exactly as :meth:`server.room.Room.tick` does, the
user's latest probe and rendered force (:meth:`ServoCore.latest`) go into
:class:`server.world.ContactInput`; :meth:`World.tick` steps the object and fits the local model,
and its :class:`shared.local_model_update.SurfacePatch` primitive with the case's gains is handed to
:meth:`ServoCore.set_patch` before the next servo tick (zero-order hold on the block boundary,
eq. 1, no extra delay: :meth:`harness_3d.Timing.decimator`).

:func:`case_result` judges a run three ways: the simulation loop (eq. 8 for P, eq. 15 for PI; the
probe as a position source), the full loop with the hand (:func:`shared.full_loop.analyze_full_loop`,
DESIGN section 6b), and the time response: the peak-to-peak probe depth over the last second of
the hold (below 0.5 mm the product calls the hold stable). :func:`product_cases` are the product's
own gains for the same object.
"""

from __future__ import annotations

import importlib
import inspect
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from haptic_collab.client.devices.profiles import get_sim_profile
from haptic_collab.client.devices.sim import HandParams
from haptic_collab.client.devices.trajectories import Press, hand_depth_for
from haptic_collab.client.servo import ServoCore
from haptic_collab.research.harness_3d import (
    PROFILE,
    SERVO_RATE_HZ,
    SIM_RATE_HZ,
    ServoPort,
    Timing,
    combined_hand,
    experiment_limits,
    local_model,
    object_world,
    place_device,
    run_multirate,
    servo_core,
)
from haptic_collab.server.objects.balloon import Balloon
from haptic_collab.server.world import ContactInput, World
from haptic_collab.shared.full_loop import analyze_full_loop
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.stability import eq8_stable, eq15_stable, rate_ratio
from haptic_collab.shared.types import FloatArray

__all__ = [
    "K_O_TARGET",
    "PAPER_CASES",
    "PROBE_DEPTH_M",
    "STABLE_HOLD_P2P_MM",
    "THETA_M",
    "Case3D",
    "CaseRun",
    "StiffBalloon",
    "Timeline3D",
    "case_result",
    "hand_json",
    "product_cases",
    "run_case",
    "stiff_balloon",
    "target_probe_depth_m",
]

#: Object stiffness at the contact of Fig. 10-11 [N/m] (the paper's 1.0 N/mm).
K_O_TARGET = 1000.0
#: How far [m] the probe is meant to press into the rest surface during the hold.
PROBE_DEPTH_M = 0.010
#: A hold whose probe depth moves less than this peak-to-peak [mm] over its last second is stable.
STABLE_HOLD_P2P_MM = 0.5
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
        A gain of the paper's Fig. 10-11, or what :func:`shared.gains.design.design_gains` picks.
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
        return object_world(self.scale)


def _top_contact(world: World) -> tuple[SurfacePatch, FloatArray]:
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
    plain = object_world()
    out0, top = _top_contact(plain)
    scale = k_o_target / out0.k_o
    stiff = object_world(scale)
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
    limits = experiment_limits(case.k_h)
    device = place_device(press, hand, limits, stiff.top)
    n_ticks = round(tl.run_s * SERVO_RATE_HZ)
    lm = local_model(
        case.k_h,
        case.i_gain,
        theta_m=THETA_M,
        release_time_s=2.0 / SIM_RATE_HZ,
        integral_limit_n=limits.max_force_n,
    )
    core = servo_core(device, lm, recorder_capacity=n_ticks + 16)
    recorder = core.recorder
    core.enable_forces()
    sim_t: list[float] = []
    disp: list[FloatArray] = []
    k_o: list[float] = []
    rest = np.asarray(obj.rest_vertices, dtype=np.float64)
    normals_rest = (
        obj.rest_normals if isinstance(obj, Balloon) else _vertex_normals(rest, world.faces)
    )

    def world_tick(n: int, states: dict[str, ContactInput]) -> dict[str, tuple[Any, float]]:
        # one simulation tick, as server.room.Room.tick: the user's latest state
        out = world.tick({"user": states["user"]})["user"]
        sim_t.append(n * (1.0 / SERVO_RATE_HZ))
        k_o.append(float(out.k_o))
        disp.append(np.einsum("ij,ij->i", world.vertices - rest, normals_rest))
        return {"user": (out.primitive, case.k_h)}

    # the client's state message (probe and force rendered on the user) after servo tick
    # sample_tick of each period; the patch applies from the World's tick on
    user = ServoPort(core, press(0.0), case.i_gain, _patch_kwargs(case, n_ratio))
    run_multirate(n_ticks, {"user": user}, world_tick, Timing.decimator(sample_tick, n_ratio))
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
        "hand": hand_json(hand),
    }


def hand_json(hand: HandParams) -> dict[str, Any]:
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
# the product's own gains (shared.gains.design, when present)
# --------------------------------------------------------------------------------------------


def product_cases(k_o: float) -> tuple[list[Case3D], list[str]]:
    """The gains the product's design picks for ``k_o`` [N/m], modes P and PI.

    Uses ``shared.gains.design.design_gains`` when it exists (no delay, the device's stiffness
    and damping limits as ``k_h_max`` and ``b_h_max`` as the client passes them, the design's
    other defaults). Returns the cases and notes on anything
    skipped (a missing design module, a servo without the probe damper or the first-order hold).
    """
    try:
        design = importlib.import_module("haptic_collab.shared.gains.design").design_gains
    except (ImportError, AttributeError):
        return [], ["shared.gains.design.design_gains is not available: product cases skipped"]
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
