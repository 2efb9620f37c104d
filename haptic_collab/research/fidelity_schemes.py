"""The rendering schemes the fidelity benchmark compares, the device they render on, and how each
is tuned (the product's design for the local models, a sweep for each peer).

:mod:`haptic_collab.research.fidelity_1d` documents the schemes and simulates them;
:class:`Rendering` says how one scheme renders one object (its :data:`RenderKind` is how the
renderer is fed), :func:`rendering_for` gives a local model's rendering from the product's gain
design or a peer's default tuning, :func:`peer_renderings` every tuning of a peer the benchmark
sweeps and :func:`scheme_tuning` the sentence the report prints for each.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

from haptic_collab.shared.full_loop import ProxyHold
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import loop_delay_ticks
from haptic_collab.shared.gains.policy import HOLD_BACK_S as REST_HOLD_BACK_S
from haptic_collab.shared.gains.policy import PLANE_DAMPERS
from haptic_collab.shared.types import FloatArray

SchemeName = Literal[
    "local-p",
    "local-pi",
    "mmt",
    "mmt-id",
    "force-jacobian",
    "direct",
    "virtual-coupling",
    "static-local",
    "direct-tdpa",
]

#: Every scheme, this project's first.
SCHEMES: tuple[SchemeName, ...] = get_args(SchemeName)

#: The schemes that are this project's local models (the rest are peers).
LOCAL_MODELS: tuple[SchemeName, ...] = ("local-p", "local-pi")

#: The way each scheme's renderer is fed (:class:`Rendering`'s ``kind``):
#: ``coupling`` the product's local model (a spring, integral and damper to the proxy the
#: simulation reports, the simulation receiving the force); ``mmt`` a plane with the stiffness
#: the simulation reports (or the client identifies: :attr:`Rendering.identifies`), at the
#: server's rest surface while the user is alone (as the product's rest plane) and at the rest
#: surface the patch implies (its surface less F / K) with another user, the simulation receiving
#: the force; ``wall`` a plane at the rest surface with a fixed stiffness, never updated;
#: ``tool`` a spring-damper to a simulated tool with mass and damping that the simulation moves
#: against the object from the probe position it receives; ``jacobian`` the simulation's force
#: and its local stiffness in contact, ``f_s + K (x - x_s)``, nothing out of contact;
#: ``direct`` the simulation's force, held.
RenderKind = Literal["coupling", "mmt", "wall", "tool", "jacobian", "direct"]


@dataclass(frozen=True, slots=True)
class DeviceModel:
    """The device every scheme renders on (the simulated Phantom Desktop's limits), SI units.

    Attributes
    ----------
    name : str
    max_force_n : float
        Force clamp [N].
    max_stiffness_n_per_m : float
        Largest stiffness [N/m] the device renders stably on its own (the virtual coupling's gain).
    max_damping_n_s_per_m : float
        Largest virtual damping [N*s/m] (the virtual coupling's damper, the PC's alpha_max).
    """

    name: str = "phantom-desktop"
    max_force_n: float = 7.9
    max_stiffness_n_per_m: float = 1000.0
    max_damping_n_s_per_m: float = 10.0


@dataclass(frozen=True, slots=True)
class TableCell:
    """One designed cell of the product's gain table (:class:`shared.gains.table.GainTable`): the
    design of grid point ``g_c = grid_ratio**cell`` [N/m], unscaled (SI units).

    Attributes
    ----------
    cell : int
        The grid index c (:meth:`shared.gains.table.GainTable.cell`).
    grid_ratio : float
        The table's grid ratio (> 1).
    k_h, i_gain, b_h, own_gain : float
        K_h [N/m], I [N/(m*s)], B_h [N*s/m], C_h [m/N] as designed for ``g_c``.
    scale_max : float
        How far the design scales with the K_o reported (:attr:`shared.gains.design.GainDesign.scale_max`).
    proxy_hold : {"zoh", "foh"}
        The proxy hold the design was checked with (the client renders each patch with its own).
    """

    cell: int
    grid_ratio: float
    k_h: float
    i_gain: float
    b_h: float
    own_gain: float
    scale_max: float
    proxy_hold: ProxyHold = "zoh"

    @classmethod
    def from_design(cls, cell: int, design: GainDesign, grid_ratio: float) -> TableCell:
        """The cell ``cell`` of a table of grid ratio ``grid_ratio`` holding ``design`` (as
        :func:`shared.gains.table.design_cell` made it, unscaled)."""
        return cls(
            cell,
            float(grid_ratio),
            design.k_h,
            design.i_gain,
            design.b_h,
            design.own_gain,
            design.scale_max,
            design.proxy_hold,
        )


@dataclass(frozen=True, slots=True)
class Rendering:
    """How one scheme renders one object (SI units).

    Attributes
    ----------
    scheme : str
        One of :data:`SCHEMES`.
    kind : str
        How the renderer is fed (:data:`RenderKind`).
    k_h, i_gain, b_h : float
        Spring K_h [N/m] (``coupling``, ``wall``, ``tool``; the cap [N/m] on the estimated
        stiffness for ``mmt`` and ``jacobian``), integral I [N/(m*s)] (``coupling``), probe damper
        [N*s/m] (every kind but ``direct``).
    proxy_hold : {"zoh", "foh"}
    theta_m : float
        Integration threshold of eq. 17 [m] (used when ``i_gain > 0``).
    release_time_s : float
        Ramp [s] driving the integral force to zero on release (section 5.1).
    passivity : bool
        Time-domain passivity observer/controller at the device port.
    passivity_bias_j : float
        Energy [J] the PC tolerates before acting.
    passivity_max_damping : float or None
        The PC's largest damping [N*s/m]; None: the device's maximum; ``math.inf``: uncapped
        (only the force clamp limits it).
    two_port : bool
        ``direct`` with ``passivity``: the two-port form for a delayed channel (module docstring).
    own_gain : float
        Own-force compensation C_h [m/N] (``coupling`` only, :mod:`shared.full_loop`): the proxy
        is the reported surface moved out by C_h times the force the simulation applied.
    jacobian_scale : float
        ``jacobian``: the fraction of the simulation's local stiffness rendered.
    follows_k_o : bool
        ``coupling``: the gains follow the K_o the simulation reports each tick, looked up in
        ``table`` as the product's client looks each patch's K_o up in its gain table
        (:meth:`shared.gains.table.GainTable.lookup`, else
        :meth:`shared.gains.table.GainTable.fallback`, :func:`table_gains`): in a designed cell,
        that cell's design scaled to the K_o reported (:meth:`shared.gains.design.GainDesign.at`);
        in a cell not designed, the nearest designed cell below it, unscaled, its own-force
        compensation keeping its share of K_o, as the client renders while that cell is designed.
    table : tuple of TableCell
        The designed cells of the client's gain table for this rendering's key (``follows_k_o``).
    planes : tuple of TableCell
        ``follows_k_o``: the verified planes (:func:`shared.gains.verified_plane.verified_plane`) of
        cells of that table, and of cells a press reaches that the table has not designed
        (checked alone: :func:`shared.gains.verified_plane.checked_plane`). Where the client's
        own-response check (:mod:`shared.gains.own_response`) verifies the K_o reported in such a
        cell, its plane renders instead of the table's design or fallback, as
        :meth:`client.session.ClientSession._render` does. Empty: never.
    plane_delay_s : float
        Time [s] from the check's first verdict in a cell to its plane rendering: 0 where the
        client checked that plane ahead, in the background (the default run); the time a check
        takes (:data:`PRODUCT_PLANE_CHECK_S`) where it checks the plane on arrival.
    rest_plane : bool
        ``follows_k_o``: the user, alone on the object, renders the rest plane the patch carries
        (:mod:`shared.gains.rest_plane`: K_h = min(K_o reported, the device's), its damper, no integral
        or compensation, the object's rest surface) where no verified plane renders and none has
        for ``rest_hold_back_s`` in this contact, as
        :meth:`client.session.ClientSession._render` does.
    rest_hold_back_s : float
        That time [s] (:data:`shared.gains.policy.HOLD_BACK_S`, the client's).
    gain_transfer_s : float
        ``coupling`` following K_o: the time [s] over which the force step of a change of gains
        in contact is carried off, as the client does (:class:`shared.local_model.LocalModel`'s
        transfer force, and a change of C_h sliding in); 0: the new gains act
        at once (each patch still with its design's proxy hold, and an integral still handed
        off with C_h > 0, as :meth:`shared.local_model.LocalModel.set_gains` does).
    identifies : bool
        ``mmt``: the plane's stiffness is the one the client's own-response check identifies
        (:func:`shared.gains.own_response.identify`: the K_o reported until it verifies the
        object, then the stiffness it holds the object to), capped at ``k_h``; else the K_o
        reported.
    tool_mass_kg, tool_damping_n_s_per_m : float
        ``tool``: the virtual tool's mass [kg] and its damping to ground [N*s/m].
    variant : str
        The peer's tuning among those swept (:func:`peer_renderings`), for the report.
    tuning : str
        How the gains were chosen, for the report.
    """

    scheme: str
    kind: RenderKind
    k_h: float = 0.0
    i_gain: float = 0.0
    b_h: float = 0.0
    proxy_hold: ProxyHold = "zoh"
    theta_m: float = 0.0
    release_time_s: float = 0.1
    passivity: bool = False
    passivity_bias_j: float = 0.0
    passivity_max_damping: float | None = None
    two_port: bool = False
    own_gain: float = 0.0
    jacobian_scale: float = 1.0
    follows_k_o: bool = False
    table: tuple[TableCell, ...] = ()
    planes: tuple[TableCell, ...] = ()
    plane_delay_s: float = 0.0
    rest_plane: bool = False
    rest_hold_back_s: float = REST_HOLD_BACK_S
    gain_transfer_s: float = 0.0
    identifies: bool = False
    tool_mass_kg: float = 0.0
    tool_damping_n_s_per_m: float = 0.0
    variant: str = ""
    tuning: str = ""


#: Integration threshold of eq. 17 the product's client renders with (``haptic client
#: --theta``, default 1 mm).
PRODUCT_THETA_M = 1e-3
#: Energy [J] the product's passivity layer tolerates (client.servo.ServoConfig's default).
PRODUCT_PASSIVITY_BIAS_J = 1e-3
#: Time [s] over which the product's client carries off the force step of new gains in contact
#: (``client.app.GAIN_TRANSFER_S``; a test keeps the two equal).
PRODUCT_GAIN_TRANSFER_S = 0.25


#: Time [s] the product's client takes to check a cell's verified plane
#: (:func:`shared.gains.verified_plane.verified_plane` in the link's design worker): measured 0.3-1.0 s
#: per check on this 2-core machine idle (2026-11-25), 6-9 s beside a benchmark. The client
#: checks the planes around the K_o reported ahead, in the background; with
#: ``haptic bench fidelity --plane-check-s`` the simulator renders each plane this long after
#: the own-response check first verifies its cell instead (a check on arrival).
PRODUCT_PLANE_CHECK_S = 2.0


def design_delay_ticks(one_way_delay_s: float, sim_rate_hz: float) -> int:
    """Delay ticks the product's client designs for over a network of this one-way delay.

    :meth:`client.session.ClientSession.delay_ticks` with a steady round trip of twice the delay
    and a state sent every half simulation period
    (:func:`shared.gains.key.loop_delay_ticks`).

    Raises
    ------
    ValueError
        A negative or non-finite delay, or a non-positive rate.
    """
    if not sim_rate_hz > 0.0:
        raise ValueError(f"sim_rate_hz must be > 0, got {sim_rate_hz!r}")
    return loop_delay_ticks(2.0 * one_way_delay_s, 0.5 / sim_rate_hz, sim_rate_hz)


#: The virtual tool's masses [kg] ``virtual-coupling`` is swept over: a stylus tip and a
#: hand-held instrument. Its damping to ground makes the tool critically damped on the coupling
#: (:func:`tool_damping`).
TOOL_MASSES_KG = (0.02, 0.1)


def tool_damping(k_c: float, b_c: float, mass_kg: float) -> float:
    """The virtual tool's damping to ground [N*s/m]: what the coupling's own damper ``b_c``
    [N*s/m] lacks of critical damping of the tool of ``mass_kg`` [kg] on the coupling spring
    ``k_c`` [N/m], ``max(0, 2 sqrt(k_c m) - b_c)`` (the tool settles on the coupling without
    ringing, the virtual environment stays passive)."""
    return max(0.0, 2.0 * math.sqrt(k_c * mass_kg) - b_c)


def plane_dampers(device: DeviceModel) -> tuple[float, ...]:
    """The probe dampers [N*s/m] every plane peer is swept over: the grid of the product's
    verified planes, :data:`shared.gains.policy.PLANE_DAMPERS` times the device's damping."""
    return tuple(f * device.max_damping_n_s_per_m for f in PLANE_DAMPERS)


def scheme_tuning(scheme: str, device: DeviceModel = DeviceModel()) -> str:
    """How ``scheme`` is tuned, in one sentence (the benchmark's report).

    Raises
    ------
    ValueError
        An unknown scheme.
    """
    b, k = device.max_damping_n_s_per_m, device.max_stiffness_n_per_m
    grid = ", ".join(f"{x:g}" for x in plane_dampers(device))
    swept = (
        "one tuning per K_o, rate, delay and user count, picked without knowing the object: the "
        "one stable with every hand of the box, then felt closest, on the spring of the K_o "
        "reported (the nominal object), then judged on every object"
    )
    planes = (
        f"capped at {k:g} N/m; probe damper {grid} N*s/m (the product's plane grid), zero- or "
        f"first-order proxy hold with another user; {swept}"
    )
    masses = " or ".join(f"{m:g}" for m in TOOL_MASSES_KG)
    text = {
        "local-p": (
            "the product's full-loop design (haptic gains) for K_o, rate and the delay ticks the "
            "client measures, own-force compensation included (docs/own-force.md); passivity "
            "layer on (the client's default)"
        ),
        "local-pi": (
            "the product's full-loop design (haptic gains) for K_o, rate and the delay ticks the "
            "client measures, own-force compensation included (docs/own-force.md: a compensated "
            "P model where that is closer to K_o); eq. 17 threshold 1 mm; passivity layer on "
            "(the client's default)"
        ),
        "mmt": (
            "model-mediated teleoperation (Mitra and Niemeyer 2008): a plane with the stiffness "
            "the simulation reports each tick, at the server's rest surface while the user is "
            "alone (what the product's rest plane gets) and at the rest surface the patch implies "
            f"(its surface less F / K) with another user; {planes}"
        ),
        "mmt-id": (
            "mmt with the stiffness identified online by the product's own-response check "
            "(shared.gains.own_response: the K_o reported until it verifies the object, then "
            f"the stiffness it holds the object to); {planes}"
        ),
        "force-jacobian": (
            "the simulation's force and local stiffness at the probe it received, f_s + K (x - "
            "x_s) at 1 kHz in contact, nothing out of contact (x_s clipped to the surface, no K "
            f"sent out of contact; Cavusoglu and Tendick 2000); K times 0.5 or 1, capped at {k:g} "
            f"N/m; probe damper {0.25 * b:g} or {b:g} N*s/m; {swept}"
        ),
        "virtual-coupling": (
            "a spring-damper to a virtual tool with mass and damping that the simulation moves "
            "against the object from the probe it receives (Colgate, Stanley and Brown 1995); "
            "the coupling is the largest impedance of the device's Z-width, "
            f"{k:g} N/m and {b:g} N*s/m, the rule of Adams and Hannaford 1999 (the device and "
            "coupling two-port absolutely stable, so any passive tool and object behind it is); "
            f"tool {masses} kg, critically damped on the coupling; rendered in contact only; "
            f"{swept}"
        ),
        "static-local": (
            "a plane at the object's rest surface with the K_o reported at the start, never "
            "updated (Mark et al. 1996's intermediate plane, placed where the object rests); "
            f"{planes}"
        ),
        "direct": "the simulation's own contact force from the probe it received, held (ZOH)",
        "direct-tdpa": (
            "direct with time-domain passivity, force clamp only (no damping cap): the one-port "
            "observer at the device (Ryu, Kwon and Hannaford 2004) or the two-port form for a "
            "delayed channel, its device side (Artigas et al. 2010: the device gives the user no "
            "more energy than the object has given back, as far as it is known there); "
            f"{swept}"
        ),
    }
    if scheme not in text:
        raise ValueError(f"unknown scheme {scheme!r}; expected one of {', '.join(SCHEMES)}")
    return text[scheme]


def peer_renderings(
    scheme: str,
    *,
    k_o: float,
    sim_rate_hz: float,
    device: DeviceModel = DeviceModel(),
    alone: bool = True,
) -> list[Rendering]:
    """Every tuning of a peer that the benchmark sweeps (:func:`scheme_tuning`), the default
    (the one :func:`rendering_for` gives) first.

    Parameters
    ----------
    scheme : str
        A peer of :data:`SCHEMES` (not a local model).
    k_o : float
        The K_o reported [N/m] (the static plane's stiffness).
    sim_rate_hz : float
        Simulation rate [Hz] (unused by today's peers; kept for tunings that depend on it).
    device : DeviceModel
    alone : bool
        The user is alone on the object (the planes stay at the server's rest surface, so their
        proxy hold does not matter); False: another user is there, and the planes that follow
        the patch are swept over both proxy holds.

    Raises
    ------
    ValueError
        An unknown scheme, a local model, or a non-positive K_o.
    """
    if not (math.isfinite(k_o) and k_o > 0.0):
        raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {k_o!r}")
    b, k = device.max_damping_n_s_per_m, device.max_stiffness_n_per_m
    dampers = (b, 0.25 * b)
    pd = plane_dampers(device)
    holds: tuple[ProxyHold, ...] = ("zoh",) if alone else ("zoh", "foh")
    tune = scheme_tuning(scheme, device) if scheme in SCHEMES else ""
    if scheme in LOCAL_MODELS:
        raise ValueError(f"{scheme} is a local model: its gains come from the product's design")
    if scheme in ("mmt", "mmt-id"):
        return [
            Rendering(
                scheme,
                "mmt",
                k_h=k,
                b_h=bh,
                proxy_hold=hold,
                identifies=scheme == "mmt-id",
                variant=f"B={bh:g}" + ("" if alone else f", {hold}"),
                tuning=tune,
            )
            for hold in holds
            for bh in pd
        ]
    if scheme == "force-jacobian":
        return [
            Rendering(
                "force-jacobian",
                "jacobian",
                k_h=k,
                b_h=bh,
                jacobian_scale=sc,
                variant=f"K x{sc:g}, B={bh:g}",
                tuning=tune,
            )
            for sc in (1.0, 0.5)
            for bh in dampers
        ]
    if scheme == "virtual-coupling":
        return [
            Rendering(
                "virtual-coupling",
                "tool",
                k_h=k,
                b_h=b,
                tool_mass_kg=m,
                tool_damping_n_s_per_m=tool_damping(k, b, m),
                variant=f"m_t={m:g}",
                tuning=tune,
            )
            for m in TOOL_MASSES_KG
        ]
    if scheme == "static-local":
        return [
            Rendering(
                "static-local", "wall", k_h=min(k_o, k), b_h=bh, variant=f"B={bh:g}", tuning=tune
            )
            for bh in pd
        ]
    if scheme == "direct":
        return [Rendering("direct", "direct", tuning=tune)]
    if scheme == "direct-tdpa":
        return [
            Rendering(
                "direct-tdpa",
                "direct",
                passivity=True,
                passivity_max_damping=math.inf,
                two_port=tp,
                variant="two-port" if tp else "one-port",
                tuning=tune,
            )
            for tp in (False, True)
        ]
    raise ValueError(f"unknown scheme {scheme!r}; expected one of {', '.join(SCHEMES)}")


class TableGains:
    """The gain tables of a batch of renderings as arrays, looked up with :meth:`gains`.

    Parameters
    ----------
    tables : sequence of tuple of TableCell
        One table per rendering (B of them); an empty table renders its own gains (``gains``
        gives NaN there).
    """

    def __init__(self, tables: Sequence[tuple[TableCell, ...]]):
        b = len(tables)
        m = max(1, max((len(t) for t in tables), default=1))
        self.valid = np.zeros((b, m), dtype=bool)
        self.cell = np.zeros((b, m), dtype=np.int64)
        self.ratio = np.full(b, 1.1)
        self.gain = np.full((5, b, m), np.nan)  # k_h, i_gain, b_h, own_gain, scale_max
        self.foh = np.zeros((b, m), dtype=bool)
        for i, t in enumerate(tables):
            for j, c in enumerate(t):
                self.valid[i, j] = True
                self.cell[i, j] = c.cell
                self.ratio[i] = c.grid_ratio
                self.gain[:, i, j] = (c.k_h, c.i_gain, c.b_h, c.own_gain, c.scale_max)
                self.foh[i, j] = c.proxy_hold == "foh"

    def has_cell(self, k_o: FloatArray) -> NDArray[np.bool_]:
        """Whether each rendering's table holds the cell of the K_o [N/m] reported (shape (B,),
        > 0): :meth:`gains_and_hold` then gives that cell's design scaled to it."""
        i = np.floor(np.log(k_o) / np.log(self.ratio) + 1e-12).astype(np.int64)
        return np.asarray((self.valid & (self.cell == i[:, None])).any(axis=1))

    def gains(self, k_o: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The first four of :meth:`gains_and_hold`."""
        k_h, i_gain, b_h, own, _ = self.gains_and_hold(k_o)
        return k_h, i_gain, b_h, own

    def gains_and_hold(
        self, k_o: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """K_h [N/m], I [N/(m*s)], B_h [N*s/m] and C_h [m/N] each rendering's client renders for
        the K_o [N/m] reported (shape (B,), > 0): :meth:`shared.gains.table.GainTable.lookup`
        where its cell is designed, else :meth:`shared.gains.table.GainTable.fallback` (the
        nearest designed cell below, unscaled, C_h keeping its share of the K_o reported and,
        more than two cells below, no integral; with none below, the nearest above scaled down
        to the cell's grid point). NaN for an empty table. Last, whether the design rendered was checked with
        a first-order hold ((B,) bool): the client renders each patch with its design's hold."""
        lr = np.log(self.ratio)
        i = np.floor(np.log(k_o) / lr + 1e-12).astype(np.int64)
        big = np.iinfo(np.int64).max
        below = self.valid & (self.cell <= i[:, None])
        has_below = below.any(axis=1)
        j = np.where(
            has_below,
            np.argmax(np.where(below, self.cell, -big), axis=1),
            np.argmin(np.where(self.valid, self.cell, big), axis=1),
        )
        rows = np.arange(len(k_o))
        c = self.cell[rows, j]
        k_h, ig, b_h, own, smax = self.gain[:, rows, j]
        g_c = self.ratio**c
        g_i = self.ratio**i
        exact = has_below & (c == i)
        s = np.where(smax > 1.0, np.clip(k_o / g_c, 1.0, np.maximum(smax, 1.0)), 1.0)
        r = g_i / g_c  # > 1 below, < 1 above
        far = (i - c > 2) & (ig > 0.0)
        k_out = np.where(exact, k_h * s, np.where(has_below, k_h, k_h * r))
        i_out = np.where(exact, ig * s, np.where(has_below, np.where(far, 0.0, ig), ig * r))
        b_out = np.where(exact | has_below, b_h, b_h * r)
        # below: C_h keeps its share of the K_o reported (no steps at the cell boundaries)
        own_out = np.where(exact, own / s, np.where(has_below, own * g_c / k_o, own / r))
        return k_out, i_out, b_out, own_out, self.foh[rows, j]


def rendering_for(
    scheme: str,
    *,
    sim_rate_hz: float,
    device: DeviceModel = DeviceModel(),
    design: GainDesign | None = None,
    k_o: float | None = None,
    table: Sequence[TableCell] = (),
    planes: Sequence[TableCell] = (),
    plane_check_s: float = 0.0,
    rest_plane: bool = True,
    rest_hold_back_s: float = REST_HOLD_BACK_S,
) -> Rendering:
    """How ``scheme`` renders an object simulated at ``sim_rate_hz`` (module docstring): a local
    model's design, or a peer's default tuning (:func:`peer_renderings`).

    Parameters
    ----------
    scheme : str
        One of :data:`SCHEMES`.
    sim_rate_hz : float
        Simulation rate [Hz] (the local models' release ramp is two simulation periods).
    device : DeviceModel
        Limits the peers are tuned to.
    design : GainDesign, optional
        The product's gains for this object, rate and delay (required for ``local-p`` and
        ``local-pi``): :class:`shared.gains.table.GainTable` with the client's key.
    k_o : float, optional
        The K_o reported [N/m] (``static-local``'s plane; default the device's stiffness).
    table : sequence of TableCell
        The client's designed cells for this key (``design``'s among them): the local model's
        gains follow the K_o the simulation reports through them (``Rendering.follows_k_o``).
        Empty: the gains of ``design`` throughout.
    planes : sequence of TableCell
        The verified planes of cells of ``table`` and of cells a press reaches that ``table``
        has not designed (:attr:`Rendering.planes`).
    plane_check_s : float
        :attr:`Rendering.plane_delay_s` [s]: 0 (default), each plane checked before the press
        reaches its cell, as the client checks the cells around the K_o reported ahead
        (:func:`shared.gains.verified_plane.ahead_cells`); :data:`PRODUCT_PLANE_CHECK_S`, a client
        whose background checks have not reached the cell yet, which checks it on arrival.
    rest_plane : bool
        :attr:`Rendering.rest_plane` for a local model following K_o (default True, as the
        client; False: the designs and verified planes alone).
    rest_hold_back_s : float
        :attr:`Rendering.rest_hold_back_s` [s] (default the client's).

    Raises
    ------
    ValueError
        An unknown scheme, or a local model without its design.
    """
    if scheme in LOCAL_MODELS:
        if design is None:
            raise ValueError(f"{scheme} needs the product's gain design")
        return Rendering(
            scheme,
            "coupling",
            k_h=design.k_h,
            i_gain=design.i_gain,
            b_h=design.b_h,
            proxy_hold=design.proxy_hold,
            theta_m=PRODUCT_THETA_M,
            release_time_s=2.0 / sim_rate_hz,
            passivity=True,  # the client's default for either model (client.app.passivity_on)
            passivity_bias_j=PRODUCT_PASSIVITY_BIAS_J,
            own_gain=design.own_gain,
            follows_k_o=bool(table),
            table=tuple(table),
            planes=tuple(planes) if table else (),
            plane_delay_s=plane_check_s,
            rest_plane=rest_plane and bool(table),
            rest_hold_back_s=rest_hold_back_s,
            gain_transfer_s=PRODUCT_GAIN_TRANSFER_S,
            tuning=scheme_tuning(scheme, device),
        )
    kk = k_o if k_o is not None else device.max_stiffness_n_per_m
    return peer_renderings(scheme, k_o=kk, sim_rate_hz=sim_rate_hz, device=device)[0]
