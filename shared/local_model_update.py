"""The surface patch and the local model update: one simulation tick's local model, from the
World through the wire to the servo tick.

Paper section 6: once per simulation tick the server fits a primitive to the current surface
near each user's probe and reports the contact's stiffness K_o, its coupling-aware K_o_eff
(DESIGN section 6) and damping B_o (Step 1); the client picks the local model's gains K_h, I
below them (Step 2) and its servo loop renders the primitive with those gains until the next
tick (zero-order hold, eq. 1, or the first-order hold of :mod:`shared.full_loop`).

One datum, two stages:

- :class:`SurfacePatch`: what the server's World computes for a user each tick (primitive,
  proxy, normal, penetration, K_o, K_o_eff, K_o_stiff, B_o, the force it applied). The wire's
  ``patch`` message (:class:`shared.protocol.Patch`) is its encoding:
  :meth:`SurfacePatch.to_wire` on the server, :meth:`SurfacePatch.from_wire` on the client (the
  primitive is validated there, once, and an absent K_o_stiff resolved to K_o, once).
- :class:`LocalModelUpdate`: that surface patch with the gains the client chose (and how it
  chose them, :class:`GainChoice`), as the servo loop renders it.

Plain Python floats, SI units: positions [m], stiffness and B_o [N/m], I
[N/(m*s)], B_h [N*s/m]. No sockets, threads or clocks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pydantic import SkipValidation

from haptic_collab.shared.checks import (
    NonNegFinite,
    PositiveFinite,
    WholePositive,
    params_dataclass,
)
from haptic_collab.shared.full_loop import ProxyHold
from haptic_collab.shared.primitives import (
    Plane,
    Primitive,
    Sphere,
    make_plane,
    make_sphere,
    moved_out,
)
from haptic_collab.shared.protocol import (
    Patch,
    PlaneModel,
    ProtocolError,
    RecommendedGains,
    SphereModel,
)
from haptic_collab.shared.types import Vec3

__all__ = [
    "GainChoice",
    "LocalModelUpdate",
    "SurfacePatch",
    "primitive_from_wire",
    "primitive_to_wire",
]


@dataclass(frozen=True, slots=True)
class SurfacePatch:
    """One user's surface patch for the next simulation period (section 6, Steps 1-2).

    Built by the server's World each tick, sent as a ``patch`` message (:meth:`to_wire`), read
    back by the client (:meth:`from_wire`).

    Attributes
    ----------
    tick : int
        Simulation tick that produced this surface (latest wins on the wire).
    primitive : shared.primitives.Plane or Sphere
        Local geometric model fitted to the current surface at the proxy [m].
    proxy : (3,) tuple of float [m]
        Closest point of the current surface to the probe (x_o).
    normal : (3,) tuple of float
        Outward unit surface normal at the proxy.
    penetration_m : float
        Signed depth of the probe past the surface [m], positive inside.
    in_contact : bool
        ``penetration_m > 0``.
    k_o : float
        Object stiffness at the contact, ``1 / C_ii`` [N/m] (paper eq. 6-8), > 0.
    k_o_eff : float
        Coupling-aware stiffness [N/m], ``<= k_o`` (DESIGN section 6): choosing ``K_h < k_o_eff``
        keeps the coupled slow loop of all nearby contacts stable.
    k_o_stiff : float
        Stiffest modal stiffness of the contact's coupled group [N/m], ``>= k_o`` (equal to
        ``k_o`` when uncoupled): a PI local model must be stable for every K_o' in
        ``[k_o_eff, k_o_stiff]`` (docs/coupled-users.md).
    b_o : float
        Object damping divided by the simulation period [N/m] (paper eq. 9); 0 without damping.
    own_force_n : float
        Force [N] along the contact normal the object received from this user in the step that
        produced this surface (Step 3), >= 0: a local model with own-force compensation renders
        against the surface moved out by C_h times it (:mod:`shared.full_loop`).
    rest_plane : shared.primitives.Plane or None
        The object's rest surface at the contact, sent while this user is the only one in the
        room (:mod:`shared.gains.rest_plane`); None otherwise.

    Raises
    ------
    TypeError
        ``primitive`` is not a Plane or Sphere, ``rest_plane`` not a Plane or None.
    ValueError
        A stiffness not finite and > 0, or B_o or the force not finite and >= 0.
    """

    tick: int
    primitive: Plane | Sphere
    proxy: Vec3
    normal: Vec3
    penetration_m: float
    in_contact: bool
    k_o: float
    k_o_eff: float
    k_o_stiff: float
    b_o: float
    own_force_n: float = 0.0
    rest_plane: Plane | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.primitive, Plane | Sphere):
            raise TypeError(
                f"primitive must be a Plane or Sphere, got {type(self.primitive).__name__}"
            )
        if self.rest_plane is not None and not isinstance(self.rest_plane, Plane):
            raise TypeError(
                f"rest_plane must be a Plane or None, got {type(self.rest_plane).__name__}"
            )
        for name in ("k_o", "k_o_eff", "k_o_stiff"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be a finite number > 0 [N/m], got {v!r}")
        for name in ("b_o", "own_force_n"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")

    @classmethod
    def of(cls, primitive: Primitive, k_o: float) -> SurfacePatch:
        """A surface patch made by hand (not by a server): ``primitive`` with stiffness ``k_o``
        [N/m], uncoupled (K_o_eff = K_o_stiff = K_o), undamped, tick 0, nothing pushed, the
        proxy at the plane's point (a sphere's top).

        Raises
        ------
        ValueError
            ``k_o`` not a finite number > 0.
        TypeError
            ``primitive`` is not a Plane or Sphere.
        """
        k = float(k_o)
        if isinstance(primitive, Sphere):
            cx, cy, cz = primitive.center
            proxy: Vec3 = (cx, cy, cz + primitive.radius)
            normal: Vec3 = (0.0, 0.0, 1.0)
        elif isinstance(primitive, Plane):
            proxy, normal = primitive.point, primitive.normal
        else:
            raise TypeError(f"primitive must be a Plane or Sphere, got {type(primitive).__name__}")
        return cls(
            tick=0,
            primitive=primitive,
            proxy=proxy,
            normal=normal,
            penetration_m=0.0,
            in_contact=False,
            k_o=k,
            k_o_eff=k,
            k_o_stiff=k,
            b_o=0.0,
        )

    def to_wire(self, gains: RecommendedGains | None = None) -> Patch:
        """This surface patch as the ``patch`` message, with the server's recommended gains.

        Raises
        ------
        pydantic.ValidationError
            A field out of the message's range (non-finite, K_o not > 0, ...).
        """
        return Patch(
            tick=int(self.tick),
            primitive=primitive_to_wire(self.primitive),
            proxy_m=self.proxy,
            normal=self.normal,
            penetration_m=float(self.penetration_m),
            in_contact=bool(self.in_contact),
            k_o=float(self.k_o),
            k_o_eff=float(self.k_o_eff),
            k_o_stiff=float(self.k_o_stiff),
            b_o=float(self.b_o),
            own_force_n=float(self.own_force_n),
            gains=gains,
            rest_plane=None
            if self.rest_plane is None
            else PlaneModel(point=self.rest_plane.point, normal=self.rest_plane.normal),
        )

    @classmethod
    def from_wire(cls, msg: Patch) -> SurfacePatch:
        """The surface patch of a server ``patch`` message (its ``gains`` are not part of it).

        An absent ``k_o_stiff`` (an uncoupled contact, or an older server) is ``k_o``; one below
        ``k_o`` counts as ``k_o``.

        Raises
        ------
        shared.protocol.ProtocolError
            ``invalid_primitive``: the patch's primitive or rest plane is not a valid plane or
            sphere.
        """
        k_o_stiff = msg.k_o if msg.k_o_stiff is None else max(msg.k_o_stiff, msg.k_o)
        rest = None if msg.rest_plane is None else primitive_from_wire(msg.rest_plane)
        return cls(
            tick=msg.tick,
            primitive=primitive_from_wire(msg.primitive),
            proxy=msg.proxy_m,
            normal=msg.normal,
            penetration_m=msg.penetration_m,
            in_contact=msg.in_contact,
            k_o=msg.k_o,
            k_o_eff=msg.k_o_eff,
            k_o_stiff=k_o_stiff,
            b_o=msg.b_o,
            own_force_n=msg.own_force_n,
            rest_plane=rest if isinstance(rest, Plane) else None,
        )


@dataclass(frozen=True, slots=True)
class GainChoice:
    """How a client chose the gains of a :class:`LocalModelUpdate` (the session's decision).

    Attributes
    ----------
    delay_ticks : int
        Delay assumed in the gain choice [simulation ticks].
    spectral_radius : float
        Worst full-loop spectral radius of the design over the hand box (below its decay limit).
    felt_stiffness_ratio_1hz : float
        Designed felt stiffness over K_o at 1 Hz (NaN: not known).
    fallback : bool
        True while the exact design for this K_o is still being computed (interim gains).
    verified : bool
        The gains passed the full-loop check for this patch's key and K_o cell (a design, or
        verified interim gains); False only for the short while that check runs after a change
        of cell or delay in mid-contact.
    source : str
        Where the gains come from (:data:`shared.gains.choose.Source`: ``design``,
        ``design-b_o`` (a damped key's shipped design for B_o = 0, checked on the damped loop),
        ``server``, ``server-interim``, ``plane``, ``rest``, ``interim``, ``covering``, ``near``,
        ``in-use``, ``fallback``).
    """

    delay_ticks: int
    spectral_radius: float
    felt_stiffness_ratio_1hz: float = math.nan
    fallback: bool = False
    verified: bool = True
    source: str = "design"


@params_dataclass(frozen=True, slots=True)
class LocalModelUpdate:
    """One simulation tick's local model: the primitive rendered, the gains, and the surface patch
    it comes from.

    Validated on construction; the servo loop applies it whole, between two ticks
    (:meth:`client.servo.ServoCore.set_patch`).

    Parameters
    ----------
    primitive : Plane or Sphere
        Local geometric model of the surface near the probe [m] (paper section 6, Step 1), as
        rendered: with own-force compensation, the surface patch's primitive moved out by
        ``own_gain * surface.own_force_n`` (:meth:`from_surface`).
    k_h : float
        Local model stiffness K_h [N/m], finite and > 0.
    i_gain : float
        Integral weight I [N/(m*s)] (eq. 12), finite and >= 0.
    b_h : float
        Probe damper B_h [N*s/m] on the backward difference of the probe position, in contact
        only; finite and >= 0 (default 0: no damper).
    proxy_hold : {"zoh", "foh"}
        ``zoh``: the new surface replaces the old at once (eq. 1); ``foh``: the penetration moves
        linearly from the old surface's to the new one's over ``hold_ticks`` servo ticks (from
        where the previous slide had got to, if this update arrived before it finished).
    hold_ticks : int
        Servo ticks of the first-order hold (N, one simulation period), a whole number >= 1.
    own_gain : float
        Own-force compensation C_h [m/N] >= 0 (:mod:`shared.full_loop`). 0: the paper's local
        model.
    surface : SurfacePatch or None
        The server's surface patch this update renders (K_o, K_o_eff, K_o_stiff, B_o, tick, the
        force the simulation applied); None: a local model set by hand, not from a server.
    choice : GainChoice or None
        How the client chose the gains (:class:`client.session.ClientSession`); None: not chosen
        by a session.
    rest_plane : bool
        ``primitive`` is the surface patch's rest plane (:mod:`shared.gains.rest_plane`), not the
        current surface: at a change between the two in contact the renderer slides the surface's
        step off over the gain transfer time (:meth:`client.render.LocalRenderer.hand_over`).

    Raises
    ------
    TypeError
        ``primitive`` is not a Plane or Sphere, ``surface`` not a SurfacePatch or ``choice`` not
        a GainChoice.
    pydantic.ValidationError
        (a ValueError naming the field) Non-finite, non-numeric or out-of-range gains,
        ``proxy_hold`` or ``hold_ticks`` (an int).
    """

    primitive: SkipValidation[Primitive]
    k_h: PositiveFinite
    i_gain: NonNegFinite
    b_h: NonNegFinite = 0.0
    proxy_hold: ProxyHold = "zoh"
    hold_ticks: WholePositive = 1
    own_gain: NonNegFinite = 0.0
    surface: SkipValidation[SurfacePatch | None] = None
    choice: SkipValidation[GainChoice | None] = None
    rest_plane: bool = False

    def __post_init__(self) -> None:
        prim = self.primitive
        if not isinstance(prim, Plane | Sphere):
            raise TypeError(f"primitive must be a Plane or Sphere, got {type(prim).__name__}")
        if self.surface is not None and not isinstance(self.surface, SurfacePatch):
            raise TypeError(f"surface must be a SurfacePatch, got {type(self.surface).__name__}")
        if self.choice is not None and not isinstance(self.choice, GainChoice):
            raise TypeError(f"choice must be a GainChoice, got {type(self.choice).__name__}")

    @property
    def recovery_m_per_n(self) -> float | None:
        """1/K_o [m/N]: a PI contact is kept while the probe is within the deformation its
        integral force holds (:class:`shared.local_model.LocalModelParams`); None without a
        surface patch (the local model keeps its own)."""
        return None if self.surface is None else 1.0 / self.surface.k_o

    @property
    def own_force_n(self) -> float:
        """The force F_s [N] >= 0 the simulation applied from this user for this surface (0
        without a surface patch)."""
        return 0.0 if self.surface is None else self.surface.own_force_n

    @classmethod
    def from_surface(
        cls,
        surface: SurfacePatch,
        *,
        k_h: float,
        i_gain: float,
        b_h: float = 0.0,
        proxy_hold: ProxyHold = "zoh",
        hold_ticks: int = 1,
        own_gain: float = 0.0,
        choice: GainChoice | None = None,
        rest: bool = False,
    ) -> LocalModelUpdate:
        """The update of a server surface patch rendered with the gains the client chose.

        With own-force compensation (``own_gain`` C_h > 0) the primitive rendered is the patch's
        moved out by ``C_h * surface.own_force_n`` (:func:`shared.primitives.moved_out`); with
        ``rest`` it is the patch's rest plane, never compensated.

        Parameters
        ----------
        surface : SurfacePatch
            The server's patch (:meth:`SurfacePatch.from_wire`).
        k_h, i_gain, b_h, proxy_hold, hold_ticks, own_gain, choice
            The local model's gains, hold and how they were chosen (see the class parameters).
        rest : bool
            Render the surface patch's rest plane (:mod:`shared.gains.rest_plane`).

        Raises
        ------
        ValueError
            Invalid gains (see the class); ``rest`` with own-force compensation or for a surface
            patch without a rest plane.
        """
        prim: Primitive = surface.primitive
        own = float(own_gain)
        if not (math.isfinite(own) and own >= 0.0):
            raise ValueError(f"own_gain must be finite and >= 0, got {own_gain!r}")
        if rest:
            if surface.rest_plane is None or own > 0.0:
                raise ValueError("rest needs a surface patch with a rest plane and own_gain 0")
            prim = surface.rest_plane
        return cls(
            primitive=moved_out(prim, own * surface.own_force_n) if own > 0.0 else prim,
            k_h=k_h,
            i_gain=i_gain,
            b_h=b_h,
            proxy_hold=proxy_hold,
            hold_ticks=hold_ticks,
            own_gain=own,
            surface=surface,
            choice=choice,
            rest_plane=bool(rest),
        )


def primitive_from_wire(model: PlaneModel | SphereModel) -> Primitive:
    """The validated primitive of a patch's ``primitive`` field (a plane's normal normalized).

    Raises
    ------
    shared.protocol.ProtocolError
        ``invalid_primitive``: a zero normal, or a sphere radius outside
        [:data:`shared.primitives.MIN_RADIUS_M`, :data:`shared.primitives.MAX_RADIUS_M`].
    """
    try:
        if isinstance(model, PlaneModel):
            return make_plane(model.point, model.normal)
        return make_sphere(model.center, model.radius)
    except ValueError as exc:
        raise ProtocolError("invalid_primitive", str(exc)) from None


def primitive_to_wire(primitive: Primitive) -> PlaneModel | SphereModel:
    """A primitive as a patch's ``primitive`` field (plane: point [m] and outward unit normal;
    sphere: centre [m] and radius [m]).

    Raises
    ------
    TypeError
        ``primitive`` is not a Plane or Sphere.
    """
    if isinstance(primitive, Plane):
        return PlaneModel(point=primitive.point, normal=primitive.normal)
    if isinstance(primitive, Sphere):
        return SphereModel(center=primitive.center, radius=primitive.radius)
    raise TypeError(f"primitive must be a Plane or Sphere, got {type(primitive).__name__}")
