"""The local model update: one simulation tick's local model, as the servo loop renders it.

Paper section 6: once per simulation tick the server fits a primitive to the current surface
near each user's probe and reports the contact's stiffness K_o, its coupling-aware K_o_eff
(DESIGN section 6) and damping B_o (Step 1); the client picks the local model's gains K_h, I
below them (Step 2) and its servo loop renders the primitive with those gains until the next
tick (zero-order hold, eq. 1, or the first-order hold of :mod:`shared.full_loop`).
:class:`LocalModelUpdate` is that one datum, from the wire to the servo tick.

Wire edge (:mod:`shared.protocol`): :meth:`LocalModelUpdate.from_wire` builds it from a ``patch``
message and the gains the client chose; :func:`primitive_from_wire` and
:func:`primitive_to_wire` convert the primitive both ways (the server builds its ``patch`` with
:func:`primitive_to_wire`: the server does not choose gains, so it has no update of its own).

Plain Python floats, SI units: positions [m], stiffness and B_o [N/m], I [N/(m*s)], B_h
[N*s/m]. No sockets, threads or clocks.
"""

from __future__ import annotations

import math

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
from haptic_collab.shared.protocol import Patch, PlaneModel, ProtocolError, SphereModel

__all__ = [
    "LocalModelUpdate",
    "primitive_from_wire",
    "primitive_to_wire",
]


@params_dataclass(frozen=True, slots=True)
class LocalModelUpdate:
    """One simulation tick's local model: primitive, rendering gains, and the contact's K_o.

    Validated on construction; the servo loop applies it whole, between two ticks
    (:meth:`client.servo.ServoCore.set_patch`).

    Parameters
    ----------
    primitive : Plane or Sphere
        Local geometric model of the surface near the probe [m] (paper section 6, Step 1).
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
    k_o : float or None
        The object's local stiffness K_o at the contact [N/m], finite and > 0; it sets the local
        model's recovery band 1/K_o (:attr:`recovery_m_per_n`). None: not known (a local model
        set by hand, not from a server).
    k_o_eff : float or None
        Coupling-aware K_o_eff [N/m] (<= K_o) the gains were chosen below; None: not known.
    k_o_stiff : float or None
        Stiffest modal stiffness K_o_stiff [N/m] (>= K_o) of the contacts coupled to this one
        (equal to K_o when uncoupled); None: not known.
    b_o : float or None
        Object damping divided by the simulation period B_o [N/m] (eq. 9), >= 0; None: not known.
    tick : int or None
        Simulation tick of the server's patch; None: not from a server.
    own_gain : float
        Own-force compensation C_h [m/N] >= 0 (:mod:`shared.full_loop`); ``primitive`` is
        already the server's surface moved out by ``own_gain * own_force_n``
        (:meth:`from_wire`). 0: the paper's local model.
    own_force_n : float
        The force F_s [N] >= 0 the simulation applied from this user for this surface.

    Raises
    ------
    TypeError
        ``primitive`` is not a Plane or Sphere.
    pydantic.ValidationError
        (a ValueError naming the field) Non-finite, non-numeric or out-of-range gains,
        ``proxy_hold`` or ``hold_ticks`` (an int), or a K_o, K_o_eff, K_o_stiff or B_o that is
        given but not finite and positive (B_o: >= 0).
    """

    primitive: SkipValidation[Primitive]
    k_h: PositiveFinite
    i_gain: NonNegFinite
    b_h: NonNegFinite = 0.0
    proxy_hold: ProxyHold = "zoh"
    hold_ticks: WholePositive = 1
    k_o: PositiveFinite | None = None
    k_o_eff: PositiveFinite | None = None
    k_o_stiff: PositiveFinite | None = None
    b_o: NonNegFinite | None = None
    tick: int | None = None
    own_gain: NonNegFinite = 0.0
    own_force_n: NonNegFinite = 0.0

    def __post_init__(self) -> None:
        prim = self.primitive
        if not isinstance(prim, Plane | Sphere):
            raise TypeError(f"primitive must be a Plane or Sphere, got {type(prim).__name__}")

    @property
    def recovery_m_per_n(self) -> float | None:
        """1/K_o [m/N]: a PI contact is kept while the probe is within the deformation its
        integral force holds (:class:`shared.local_model.LocalModelParams`); None without K_o
        (the local model keeps its own)."""
        return None if self.k_o is None else 1.0 / self.k_o

    @classmethod
    def from_wire(
        cls,
        msg: Patch,
        *,
        k_h: float,
        i_gain: float,
        b_h: float = 0.0,
        proxy_hold: ProxyHold = "zoh",
        hold_ticks: int = 1,
        own_gain: float = 0.0,
    ) -> LocalModelUpdate:
        """The update of a server ``patch`` rendered with the gains the client chose.

        With own-force compensation (``own_gain`` C_h > 0) the primitive rendered is the patch's
        moved out by ``C_h * msg.own_force_n`` (:func:`shared.primitives.moved_out`).

        Parameters
        ----------
        msg : shared.protocol.Patch
            The server's patch: primitive, ``tick``, ``k_o``, ``k_o_eff``, ``k_o_stiff`` (absent:
            K_o, an uncoupled contact) and ``b_o``.
        k_h, i_gain, b_h, proxy_hold, hold_ticks, own_gain
            The local model's gains and hold (see the class parameters).

        Raises
        ------
        shared.protocol.ProtocolError
            ``invalid_primitive``: the patch's primitive is not a valid plane or sphere.
        ValueError
            Invalid gains (see the class).
        """
        prim = primitive_from_wire(msg.primitive)
        own = float(own_gain)
        if not (math.isfinite(own) and own >= 0.0):
            raise ValueError(f"own_gain must be finite and >= 0, got {own_gain!r}")
        return cls(
            primitive=moved_out(prim, own * msg.own_force_n) if own > 0.0 else prim,
            k_h=k_h,
            i_gain=i_gain,
            b_h=b_h,
            proxy_hold=proxy_hold,
            hold_ticks=hold_ticks,
            k_o=msg.k_o,
            k_o_eff=msg.k_o_eff,
            k_o_stiff=msg.k_o_stiff_or_k_o(),
            b_o=msg.b_o,
            tick=msg.tick,
            own_gain=own,
            own_force_n=msg.own_force_n,
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
