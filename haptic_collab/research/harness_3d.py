"""The 3-D harness both World drivers share: the object's World, the simulated device and hand,
the product's servo, and the multirate loop that ticks them in-process.

:mod:`haptic_collab.research.reproduce_3d` (the paper's Fig. 10-11) and
:mod:`haptic_collab.research.fidelity_3d` (the fidelity benchmark's 3-D cells) run the same
blocks, every one the product's own code, tick by tick, with integer ticks and no clock, socket or
thread (time is ``tick / rate``):

object
    :func:`object_world`: :func:`server.main.build_world` around ``--mesh`` (the default water
    balloon) with ``--stiffness-scale``, stepped at :data:`SIM_RATE_HZ` (``fem:NAME``: the FEM
    solid of that surface in :data:`FEM_MATERIAL_3D`); :func:`reused_world` the same with its
    object built once per process and reset for each run (the fidelity cells).
user
    :func:`place_device`: a :class:`client.devices.sim.SimDevice` on the :data:`PROFILE` profile
    with a :class:`client.devices.sim.HandParams` hand following a target, its workspace centred on
    the contact, with :func:`experiment_limits` (no motor-heating limit, the stiffness limit raised
    to the K_h under test); :func:`servo_core`: a :class:`client.servo.ServoCore` with a local
    model of eq. 12 and eq. 17's fixed threshold (:func:`local_model`), ticked at
    :data:`SERVO_RATE_HZ`; :class:`ServoPort` the user the World talks to.
loop
    :func:`run_multirate`: every servo tick each user ticks; every :data:`RATE_RATIO` servo ticks
    the World ticks once with each user's latest state and hands each user what it renders next,
    with the delays of a :class:`Timing` (the paper's decimator, or a network delay both ways).

What each driver records, and what the World computes from the users' states, stays in the
driver (the callbacks of :func:`run_multirate` and :class:`ServoPort`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from haptic_collab.client.devices.base import DeviceLimits
from haptic_collab.client.devices.profiles import get_sim_profile
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.server.main import ServerOptions, build_world, world_around
from haptic_collab.server.world import ContactInput, World
from haptic_collab.shared.full_loop import Hand
from haptic_collab.shared.local_model import LocalModelParams, ThresholdParams

#: Servo rate 1/T [Hz] (the paper's experiment and the product's servo).
SERVO_RATE_HZ = 1000.0
#: Simulation rate 1/(N*T) [Hz] of the World (the paper's 20 Hz).
SIM_RATE_HZ = 20.0
#: Servo ticks per World tick, N.
RATE_RATIO = round(SERVO_RATE_HZ / SIM_RATE_HZ)
#: The simulated device (client.devices.profiles).
PROFILE = "phantom-desktop"
#: Prefix of a mesh name that makes the object the FEM solid of that surface (``--object fem``),
#: in :data:`FEM_MATERIAL_3D`: ``fem:box`` is the stress set's box as a liver-like solid.
FEM_PREFIX = "fem:"
#: The solid material of the FEM objects (:mod:`server.solid_materials`).
FEM_MATERIAL_3D = "liver"


def world_options(stiffness_scale: float = 1.0, mesh: str = "balloon") -> ServerOptions:
    """The server's options for ``mesh`` scaled by ``stiffness_scale``, at :data:`SIM_RATE_HZ`."""
    if mesh.startswith(FEM_PREFIX):
        return ServerOptions(
            sim_rate_hz=SIM_RATE_HZ,
            stiffness_scale=stiffness_scale,
            object="fem",
            mesh=mesh[len(FEM_PREFIX) :],
            material=FEM_MATERIAL_3D,
        )
    return ServerOptions(sim_rate_hz=SIM_RATE_HZ, stiffness_scale=stiffness_scale, mesh=mesh)


def object_world(stiffness_scale: float = 1.0, mesh: str = "balloon") -> World:
    """A fresh World (object at rest) of :func:`world_options`.

    Raises
    ------
    ValueError
        A scale that is not a finite number > 0, or an unknown mesh
        (:func:`server.main.build_world`).
    """
    world: World = build_world(world_options(stiffness_scale, mesh))
    return world


#: Objects :func:`reused_world` built in this process, by (stiffness scale, mesh).
_BUILT: dict[tuple[float, str], Any] = {}


def reused_world(stiffness_scale: float = 1.0, mesh: str = "balloon") -> World:
    """:func:`object_world`, its object built once in this process and reset to rest for every
    later call with the same arguments: a FEM solid's start-up (volume mesh, factorisation,
    modes) takes 4-5 s on the test machine, a 3-D fidelity cell's run about 0.5 s. The patch cache
    is kept: its solves are the object's own whichever run made them, and a fresh object starts
    with the two its build solved (the top and the side, for the log), which a cleared cache
    would solve again in another batch, a few ulps apart (enough to move an unstable cell's
    energy by 2 %). For callers that use one World at a time: a World from an earlier call must
    not be ticked after the next call (they share the object).

    Raises
    ------
    ValueError
        As :func:`object_world`.
    """
    key = (float(stiffness_scale), mesh)
    obj = _BUILT.get(key)
    if obj is None:
        world = object_world(stiffness_scale, mesh)
        _BUILT[key] = world.obj
        return world
    obj.reset()
    again: World = world_around(obj, world_options(stiffness_scale, mesh))
    return again


def combined_hand(hand: HandParams, profile: str = PROFILE) -> Hand:
    """The hand as the probe feels it: the simulated hand plus the device's mass and damping."""
    prof = get_sim_profile(profile)
    return Hand(
        mass_kg=hand.mass_kg + prof.mass_kg,
        damping_n_s_per_m=hand.damping_n_s_per_m + prof.limits.damping_n_s_per_m,
        stiffness_n_per_m=hand.stiffness_n_per_m,
    )


def experiment_limits(k_h: float, **changes: Any) -> DeviceLimits:
    """The :data:`PROFILE` device's limits for an experiment rendering K_h = ``k_h`` [N/m].

    ``changes`` replace limits (:class:`client.devices.base.DeviceLimits` fields); the
    motor-heating limit (client/thermal.py) is off, as the experiments' seconds-long presses are
    compared on their loops, and the stiffness limit is raised to ``k_h`` when that is above it
    (the paper ran 1.2 N/mm on its Phantom; the profile's limit is the product's own safety
    margin, not what these experiments are about).
    """
    limits = replace(get_sim_profile(PROFILE).limits, **changes, max_continuous_force_n=None)
    if k_h > limits.max_stiffness_n_per_m:
        limits = replace(limits, max_stiffness_n_per_m=k_h)
    return limits


def place_device(
    target: Callable[[float], Any],
    hand: HandParams,
    limits: DeviceLimits,
    at: tuple[float, float, float],
    *,
    device_cls: type[SimDevice] = SimDevice,
    enable_forces: bool = False,
    **kwargs: Any,
) -> SimDevice:
    """The simulated :data:`PROFILE` device, opened, its workspace centred on ``at`` [m] and its
    hand pulled toward ``target(t)`` [m] (``device_cls`` and ``kwargs``: a subclass and its own
    arguments; ``enable_forces``: enable the device's forces at once)."""
    dev = device_cls(
        get_sim_profile(PROFILE),
        target,  # type: ignore[arg-type]
        hand,
        limits=limits.centered_at(at),
        servo_period_s=1.0 / SERVO_RATE_HZ,
        **kwargs,
    )
    dev.open()
    if enable_forces:
        dev.enable_forces()
    return dev


def local_model(
    k_h: float, i_gain: float, *, theta_m: float, release_time_s: float, integral_limit_n: float
) -> LocalModelParams:
    """The local model of eq. 12 at :data:`SERVO_RATE_HZ` with eq. 17's fixed threshold
    ``theta_m`` [m], the integral released over ``release_time_s`` [s] and limited to
    ``integral_limit_n`` [N]."""
    return LocalModelParams(
        k_h=k_h,
        i_gain=i_gain,
        servo_period_s=1.0 / SERVO_RATE_HZ,
        threshold=ThresholdParams(mode="fixed", theta_m=theta_m),
        release_time_s=release_time_s,
        integral_limit_n=integral_limit_n,
    )


def servo_core(
    device: SimDevice,
    lm: LocalModelParams,
    *,
    recorder_capacity: int,
    **config: Any,
) -> ServoCore:
    """The product's servo on ``device`` with the local model ``lm``, a telemetry recorder of
    ``recorder_capacity`` rows and ``ServoConfig(servo_rate_hz=SERVO_RATE_HZ, **config)``."""
    return ServoCore(
        device,
        ServoConfig(servo_rate_hz=SERVO_RATE_HZ, **config),
        local_model=lm,
        recorder=TelemetryRecorder(capacity=recorder_capacity),
    )


@dataclass(frozen=True)
class Timing:
    """When the World ticks and when what it receives and sends arrives, in whole servo ticks.

    The World ticks at the start of every servo tick ``n`` with ``n % rate_ratio == phase``, before
    the users tick; it uses each user's state published after servo tick ``n - 1 - up`` (the
    user's start state when there is none yet) and its output reaches each user from servo tick
    ``n + down`` (applied before that tick).

    Attributes
    ----------
    phase, up, down : int
        >= 0, ``phase < rate_ratio``.
    rate_ratio : int
        Servo ticks per World tick, N.
    """

    phase: int
    up: int
    down: int
    rate_ratio: int = RATE_RATIO

    def __post_init__(self) -> None:
        if not (self.rate_ratio >= 1 and 0 <= self.phase < self.rate_ratio):
            raise ValueError(f"phase must be in [0, {self.rate_ratio}), got {self.phase!r}")
        if self.up < 0 or self.down < 0:
            raise ValueError(f"delays must be >= 0 ticks, got up {self.up!r}, down {self.down!r}")

    @classmethod
    def decimator(cls, sample_tick: int, rate_ratio: int = RATE_RATIO) -> Timing:
        """The paper's timing (eq. 1): the World ticks at the start of each period with the state
        of servo tick ``sample_tick`` of the period before (0: the paper's decimator, a whole
        period of computation; N - 1: the freshest), and its output holds from that same tick."""
        return cls(phase=0, up=rate_ratio - 1 - sample_tick, down=0, rate_ratio=rate_ratio)

    @classmethod
    def network(cls, delay_ticks: int, rate_ratio: int = RATE_RATIO) -> Timing:
        """A one-way delay of ``delay_ticks`` both ways: the World ticking after servo tick ``n``
        (``n % N == 0``) uses the state the user published after tick ``n - delay_ticks``, and
        its output reaches the user from tick ``n + 1 + delay_ticks`` (one tick of computation)."""
        return cls(phase=1 % rate_ratio, up=delay_ticks, down=delay_ticks, rate_ratio=rate_ratio)


class Port(Protocol):
    """One user as the loop sees it: it ticks, publishes a state, receives the World's output."""

    def start_state(self) -> Any:
        """What the World sees of the user before the first state arrives."""
        ...

    def tick(self, n: int) -> None:
        """Servo tick ``n`` (time ``n / SERVO_RATE_HZ``), with whatever the driver records."""
        ...

    def state(self) -> Any:
        """The state the user would send now (None: nothing to send)."""
        ...

    def receive(self, message: Any) -> None:
        """Apply what the World sent, before the next tick."""
        ...


class ServoPort:
    """A user whose :class:`client.servo.ServoCore` renders the patches the World sends.

    It sends the probe and the force the servo rendered (:meth:`ServoCore.latest`, the client's
    state message); each message from the World is ``(primitive, K_h)``, handed to
    :meth:`ServoCore.set_patch` with ``i_gain`` and ``patch_kwargs``. ``after_tick(n)``, when
    given, runs after each servo tick (the driver's records).
    """

    __slots__ = ("core", "start_probe", "i_gain", "patch_kwargs", "after_tick")

    def __init__(
        self,
        core: ServoCore,
        start_probe: Any,
        i_gain: float,
        patch_kwargs: Mapping[str, Any],
        after_tick: Callable[[int], None] | None = None,
    ) -> None:
        self.core = core
        self.start_probe = np.asarray(start_probe, dtype=np.float64)
        self.i_gain = i_gain
        self.patch_kwargs = dict(patch_kwargs)
        self.after_tick = after_tick

    def start_state(self) -> ContactInput:
        """The starting probe and no force."""
        return ContactInput(probe=self.start_probe, force=np.zeros(3))

    def tick(self, n: int) -> None:
        """One servo tick at ``n / SERVO_RATE_HZ``, then ``after_tick(n)``."""
        self.core.tick(n * (1.0 / SERVO_RATE_HZ))
        if self.after_tick is not None:
            self.after_tick(n)

    def state(self) -> ContactInput | None:
        """The servo's latest probe and rendered force (None before the first tick)."""
        snap = self.core.latest()
        if snap is None:
            return None
        return ContactInput(
            probe=np.asarray(snap.probe_m, dtype=np.float64),
            force=np.asarray(snap.force_n, dtype=np.float64),
        )

    def receive(self, message: Any) -> None:
        """``(primitive, K_h)``: the next patch, applied from the next tick."""
        primitive, k_h = message
        self.core.set_patch(primitive, k_h, self.i_gain, **self.patch_kwargs)


#: ``world_tick(n, states)``: the World's tick at the start of servo tick ``n`` with each user's
#: state; returns what each user receives (users left out receive nothing).
WorldTick = Callable[[int, dict[str, Any]], Mapping[str, Any]]


def run_multirate(
    n_ticks: int, users: Mapping[str, Port], world_tick: WorldTick, timing: Timing
) -> None:
    """Run ``n_ticks`` servo ticks of every user against one World (module docstring).

    At the start of each servo tick ``n``: the World ticks when ``timing`` says so, with the state
    each user published for it (its :meth:`Port.start_state` when none has); then each user, in
    order, receives what the World sent for tick ``n``, ticks, and publishes its state when a World
    tick will use it. A World tick that would fall after the last servo tick is not run.
    """
    N, phase, up, down = timing.rate_ratio, timing.phase, timing.up, timing.down
    sent: dict[str, dict[int, Any]] = {u: {} for u in users}
    inbox: dict[str, dict[int, Any]] = {u: {} for u in users}
    ports = list(users.items())
    for n in range(n_ticks):
        if n % N == phase:
            states = {u: sent[u].pop(n) if n in sent[u] else p.start_state() for u, p in ports}
            for u, message in world_tick(n, states).items():
                inbox[u][n + down] = message
        publish = (n + 1 + up) % N == phase
        for u, p in ports:
            message = inbox[u].pop(n, None)
            if message is not None:
                p.receive(message)
            p.tick(n)
            if publish:
                s = p.state()
                if s is not None:
                    sent[u][n + 1 + up] = s
