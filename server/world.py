"""The sans-I/O simulation core: one deformable object, every user's contact, once per tick.

The room calls :meth:`World.tick` once per simulation period N*T with each user's latest probe
position and last rendered force, and sends each user the returned surface patch
(:class:`shared.local_model_update.SurfacePatch`; DESIGN section 4). One tick is paper section 6:

1. **Step 3** - each user's last force rendered *on the user* (outward) is applied to the object
   as a push ``f = max(0, force . n)`` along the inward normal ``-n``, spread over a finger-pad
   patch at the contact: the proxy of the user's probe on the local model sent last tick (which
   *is* the current surface near the probe, Step 1), or the exact closest point of the current
   surface for a new user or a probe that jumped. The force is applied whatever the probe's
   position relative to that surface: the paper's Step 3 uses "the last force returned to the
   haptic device", and a surface that overshot past the probe still receives the integral force
   the local model is ramping down (section 5.1). Gating the load by the server's own geometry
   instead drops that force at once and turns such an overshoot into a sustained period-2
   oscillation. Only probes farther than ``reach_m`` outside (a stale or bogus report) push nothing.
2. The object steps one simulation period (eq. 6 static, or eq. 9 visco-elastic).
3. **Step 1** - every probe is located on the *new* surface: proxy, outward normal, signed
   penetration, and a plane or sphere primitive fitted there. A probe in contact keeps a proxy
   that follows the surface (a god-object, :func:`server.contacts.track_proxy`): carried by the
   deformation and slid from where it was down the distance to the probe, it never jumps to a
   nearer point on another part of the object (the far side of a thin part, the other wall of a
   crease, a part a deep compensated probe happens to be nearer). A probe that was outside and is
   inside now starts its proxy where it crossed the surface (:func:`server.contacts.segment_entry`);
   a probe out of contact gets the closest point of the surface.
4. **Step 2 inputs** - per contact ``K_o = 1 / C_ii``, ``B_o`` (eq. 9) and the coupling-aware
   ``K_o_eff`` (DESIGN section 6) over the contacts that touch or nearly touch the surface.
5. **The rest plane** - to the only user of the tick, the object's rest surface at the contact:
   the plane through the proxy's material point at rest with the rest normal there
   (:mod:`shared.gains.rest_plane`; the client may render it instead of the current surface while
   alone). With another user in the room, none: a user whose rendering switched whenever another
   came near would feel the switch, and would feel the other's push only through the design.

Nothing here uses sockets, threads, asyncio or clocks; time advances one tick per call.
Bad values never crash a tick: a non-finite probe or force skips that user's load, and the
user's output is computed at the last finite probe (or the top of the object).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from haptic_collab.server.contact_stiffness import K_O_MAX, effective_stiffness, stiff_stiffness
from haptic_collab.server.contacts import (
    SurfaceIndex,
    SurfacePoint,
    closest_point,
    fit_plane,
    fit_sphere,
    segment_entry,
    surface_normal,
    track_proxy,
)
from haptic_collab.server.objects import AdmittanceObject
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.modal_loop import ContactModes
from haptic_collab.shared.primitives import Plane, Sphere, make_plane
from haptic_collab.shared.rates import Rates
from haptic_collab.shared.types import FloatArray, Vec3


@dataclass(frozen=True, eq=False)
class ContactInput:
    """One user's input to a tick.

    Attributes
    ----------
    probe : (3,) float [m]
        Haptic interface point x_h.
    force : (3,) float [N]
        The last force the user's device rendered ON THE USER (outward: it pushes the probe out).
        The object receives the opposite (section 6, Step 3).
    """

    probe: FloatArray
    force: FloatArray


#: A probe that moved more than this [m] since last tick is located exactly before loading.
_RELOCATE_M = 0.01


@dataclass(frozen=True, eq=False)
class _UserState:
    """What the world remembers of a user between ticks.

    The last finite probe, the primitive sent, the load patch's key, and where the proxy was on
    the surface (its face and barycentric coordinates, and the probe's penetration there), with
    that point's material point and rest normal (:meth:`World._material_of`), which the next
    tick's load (Step 3) starts from.
    """

    probe: FloatArray
    primitive: Plane | Sphere
    key: int
    surface: SurfacePoint
    rest_point: FloatArray
    rest_normal: FloatArray


@dataclass(frozen=True)
class Coupling:
    """Every user's contact of one tick as the coupled stability sees it (the server's gain
    advisor checks coupled pairs from it, :meth:`server.gains.GainAdvisor.hold_pairs`).

    Attributes
    ----------
    names : tuple of str
        The users, in the order of the arrays.
    compliance : (M, M) float [m/N]
        The contacts' normal compliance ``C_ij`` (the object's ``contact_compliance``), every user
        in it, near the surface or not: ``K_o,i = 1 / C_ii``.
    penetration_m : (M,) float [m]
        Each probe's penetration (negative: outside the surface by that much).
    proximity_m : float
        Users with a penetration above ``-proximity_m`` take part in ``K_o_eff`` and ``K_o_stiff``.
    """

    names: tuple[str, ...]
    compliance: FloatArray
    penetration_m: FloatArray
    proximity_m: float


def _finite3(value: object) -> FloatArray | None:
    """The value as a (3,) float64 array if it is 3 finite numbers, else None."""
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    if arr.shape != (3,) or not np.isfinite(arr).all():
        return None
    return arr


class World:
    """The authoritative simulation: one admittance object and every user's contact.

    Parameters
    ----------
    obj : AdmittanceObject
        The deformable object, e.g. :class:`server.objects.balloon.Balloon`.
    primitive : {"plane", "sphere"}
        Local geometric model sent to users (a sphere falls back to a plane where the surface
        is flat or concave).
    proximity_m : float
        Contacts within this distance [m] outside the surface (or inside it) take part in the
        coupled stability of ``k_o_eff``.
    reach_m : float
        A reported force is applied (Step 3) unless the probe is more than this [m] outside the
        local model it was rendered against.
    rates : shared.rates.Rates, optional
        The servo and simulation rates the server runs at (:func:`server.main.build_rates`);
        the object's ``sim_period_s`` must be their N*T. Kept as :attr:`rates` for the room.
    proxy : {"follow", "closest"}
        ``follow`` (default): a proxy in contact follows the surface from where it was
        (god-object, :func:`server.contacts.track_proxy`). ``closest``: the paper's Step 1 read
        literally, the closest point of the current surface every tick (it jumps across thin
        parts and creases; kept for comparison, ``haptic bench server``).

    Raises
    ------
    ValueError
        Unknown primitive or proxy, ``proximity_m`` or ``reach_m`` not finite and >= 0, or an
        object whose simulation period is not the one of ``rates``.
    """

    def __init__(
        self,
        obj: AdmittanceObject,
        primitive: Literal["plane", "sphere"] = "plane",
        proximity_m: float = 0.005,
        reach_m: float = 0.03,
        rates: Rates | None = None,
        proxy: Literal["follow", "closest"] = "follow",
    ) -> None:
        if proxy not in ("follow", "closest"):
            raise ValueError(f"proxy must be 'follow' or 'closest', got {proxy!r}")
        #: How a proxy in contact is found: following the surface, or the closest point.
        self.proxy = proxy
        if rates is not None:
            rates.check_sim_period(float(obj.sim_period_s), "the object")
        #: The rates the world was built for (None: only the object's own period is known).
        self.rates = rates
        if primitive not in ("plane", "sphere"):
            raise ValueError(f"primitive must be 'plane' or 'sphere', got {primitive!r}")
        prox = float(proximity_m)
        if not (math.isfinite(prox) and prox >= 0.0):
            raise ValueError(f"proximity_m must be finite and >= 0, got {proximity_m!r}")
        self.obj = obj
        self.primitive: Literal["plane", "sphere"] = primitive
        self.proximity_m = prox
        reach = float(reach_m)
        if not (math.isfinite(reach) and reach >= 0.0):
            raise ValueError(f"reach_m must be finite and >= 0, got {reach_m!r}")
        self.reach_m = reach
        self._index = SurfaceIndex.build(obj.rest_vertices, obj.faces)
        self._faces = np.ascontiguousarray(obj.faces, dtype=np.int32)
        self._faces.setflags(write=False)
        rest = self._index.rest_vertices
        # every face's rest unit normal (zero for a degenerate face), once: the rest surface
        # never changes, and the material point of every contact needs its face's
        tri = rest[self._index.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.sqrt(np.einsum("ij,ij->i", n, n))
        self._rest_normals = np.divide(
            n, length[:, None], out=np.zeros_like(n), where=length[:, None] > 0.0
        )
        self._rest_normal_ok = length > 0.0
        lo, hi = rest.min(axis=0), rest.max(axis=0)
        self._bounds = np.stack([lo, hi])
        self._center = 0.5 * (lo + hi)
        self._radius = float(np.max(np.linalg.norm(rest - self._center, axis=1)))
        self._current = np.asarray(obj.vertices, dtype=np.float64)
        self._bound = float(obj.max_displacement_m)
        self._tick = 0
        self._users: dict[str, _UserState] = {}
        #: The last tick's contacts as the coupled stability saw them (:class:`Coupling`).
        self.coupling = Coupling((), np.zeros((0, 0)), np.zeros(0), self.proximity_m)

    # ------------------------------------------------------------------ state
    @property
    def vertices(self) -> FloatArray:
        """(n, 3) float64 [m] current surface vertices (read-only view, replaced each tick)."""
        view = self._current.view()
        view.setflags(write=False)
        return view

    @property
    def faces(self) -> npt.NDArray[np.int32]:
        """(m, 3) int32 triangle vertex indices, outward winding."""
        return self._faces

    @property
    def n_vertices(self) -> int:
        """Number of surface vertices n."""
        return len(self._current)

    def modal_contact(self, name: str) -> int | None:
        """The object's key of ``name``'s contact where the object has modes to check gains on
        (:meth:`server.objects.fem.FemSolid.contact_modes`), else None (no such object, no
        modes, or no such user)."""
        user = self._users.get(name)
        if user is None or not getattr(self.obj, "has_contact_modes", False):
            return None
        return int(user.key)

    def contact_modes(self, name: str) -> ContactModes | None:
        """The modes of ``name``'s contact (:meth:`modal_contact`), or None."""
        key = self.modal_contact(name)
        return None if key is None else self.obj.contact_modes(key)  # type: ignore[attr-defined]

    @property
    def tick_count(self) -> int:
        """Ticks simulated so far."""
        return self._tick

    @property
    def sim_period_s(self) -> float:
        """Simulation period N*T [s] of one tick (the object's; equal to ``rates.sim_period_s``)."""
        return float(self.obj.sim_period_s)

    @property
    def rest_center(self) -> FloatArray:
        """(3,) float64 [m] centre of the rest bounding box."""
        return self._center.copy()

    @property
    def rest_radius_m(self) -> float:
        """Largest distance [m] of a rest vertex from :attr:`rest_center`."""
        return self._radius

    @property
    def rest_bounds(self) -> FloatArray:
        """(2, 3) float64 [m] rest bounding box ``[min, max]``; the top is ``max[2]``."""
        return self._bounds.copy()

    def restore(self, tick: int) -> None:
        """Take the object's surface as it is now and go on counting from tick number ``tick``.

        For an object whose state was set from outside between ticks (a room made again from
        its snapshot, :mod:`server.snapshots`): the surface the users and viewers get is then
        the object's, and every user is forgotten (a restored room has none yet).

        Raises
        ------
        ValueError
            ``tick`` negative.
        """
        if int(tick) < 0:
            raise ValueError(f"tick must be >= 0, got {tick}")
        self._current = np.asarray(self.obj.vertices, dtype=np.float64)
        self._bound = float(self.obj.max_displacement_m)
        self._tick = int(tick)
        self._users = {}

    # ------------------------------------------------------------------ tick
    def _locate(self, probe: FloatArray, user: _UserState | None = None) -> SurfacePoint:
        """The user's proxy on the current surface (Step 1), given what it was last tick.

        In contact last tick: the proxy follows the surface from where it was
        (:func:`server.contacts.track_proxy`) as long as the probe stays inside along it. Outside
        last tick and inside now: the proxy starts where the probe's path crossed the surface
        and slides on from there. Otherwise (a new user, a probe in free space): the closest
        point of the surface.
        """
        if user is not None and self.proxy == "follow":
            last = user.surface
            start: SurfacePoint | None = None
            if last.penetration_m > 0.0 and last.bary is not None:
                start = last
            else:
                start = segment_entry(self._index, self._current, user.probe, probe, self._bound)
            if start is not None and start.bary is not None:
                here = track_proxy(self._index, self._current, probe, start.face, start.bary)
                if here.penetration_m > 0.0:
                    return here
        return closest_point(self._index, self._current, probe, self._bound)

    def _probe_for(self, name: str, inp: ContactInput) -> FloatArray:
        probe = _finite3(getattr(inp, "probe", None))
        if probe is not None:
            return probe
        last = self._users.get(name)
        if last is not None:
            return last.probe
        return self._center + np.array([0.0, 0.0, self._radius + self.proximity_m + 0.01])

    def _load_point(self, name: str, probe: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        """Where the user's force acts this tick: ``(point, outward normal, penetration)``.

        The local model the user's device rendered against (sent last tick) is the current
        surface near the probe (section 6, Step 1), so its proxy and normal at the probe are the
        contact. A user without one, or whose probe jumped more than ``_RELOCATE_M`` since, is
        located exactly on the current surface.
        """
        user = self._users.get(name)
        if user is not None:
            jump = probe - user.probe
            if float(jump @ jump) <= _RELOCATE_M**2:
                prim = user.primitive
                e, nx, ny, nz = prim.contact(float(probe[0]), float(probe[1]), float(probe[2]))
                proxy = np.asarray(prim.proxy(float(probe[0]), float(probe[1]), float(probe[2])))
                return proxy, np.array([nx, ny, nz]), e
        here = self._locate(probe, user)
        return here.point, here.normal, here.penetration_m

    def _material_of(self, s: SurfacePoint) -> tuple[FloatArray, FloatArray]:
        """Where the surface point ``s`` was at rest, and the rest normal of its face: the patch
        centres are rest positions, and a part that moved or turned by centimetres (a bent FEM
        part) must be loaded at its own patch, not at the one now nearest in space."""
        face = int(s.face)
        tri = self._index.rest_vertices[self._index.faces[face]]
        bary = s.bary
        if bary is None:
            bary = np.full(3, 1.0 / 3.0)
        normal = self._rest_normals[face] if self._rest_normal_ok[face] else np.asarray(s.normal)
        return bary @ tri, normal

    def _rest_plane(self, s: SurfacePoint, rest_point: FloatArray) -> Plane | None:
        """The rest surface's tangent plane at the material point ``rest_point`` of ``s``, with
        the rest vertex normals interpolated there (as the current surface's patch); None where
        ``s`` has no barycentric coordinates."""
        if s.bary is None:
            return None
        n = surface_normal(self._index, self._index.rest_vertices, s.face, s.bary)
        return make_plane(_t3(rest_point), _t3(n))

    def _material(
        self, point: FloatArray, normal: FloatArray, user: _UserState | None
    ) -> tuple[FloatArray, FloatArray]:
        """The rest-space point and normal of a load at ``point`` near the user's last located
        surface point (moved back by that point's displacement); the point itself without one."""
        if user is None:
            return point, normal
        return point - (user.surface.point - user.rest_point), user.rest_normal

    def patches_ahead(self, limit: int = 4) -> list[int]:
        """Up to ``limit`` uncached patch centres next to the users' current ones, for solving
        off the tick (:class:`server.prefetch.PatchPrefetcher`); [] for an object that cannot
        prefetch (:class:`server.objects.patches.PatchedSurface`)."""
        ahead = getattr(self.obj, "patches_ahead", None)
        if ahead is None or not self._users:
            return []
        return list(ahead([u.key for u in self._users.values()], int(limit)))

    def tick(
        self, inputs: Mapping[str, ContactInput], tick: int | None = None
    ) -> dict[str, SurfacePatch]:
        """Apply every user's force, step the object one period, and fit every local model.

        Parameters
        ----------
        inputs : mapping user id -> ContactInput
            Users absent from the mapping neither push nor get an output (their state is
            forgotten).
        tick : int, optional
            The number the patches carry (the room's schedule, which skips ticks it missed);
            default: this world's count of ticks (:attr:`tick_count`) after this one.

        Returns
        -------
        dict user id -> shared.local_model_update.SurfacePatch, same keys (and order) as
        ``inputs``.
        """
        names = list(inputs)
        # Step 3: each user's last rendered force, opposite, on the object at its contact.
        keys: list[int] = []
        forces: list[float] = []
        pushed: dict[str, float] = {}
        for name in names:
            inp = inputs[name]
            probe = _finite3(getattr(inp, "probe", None))
            force = _finite3(getattr(inp, "force", None))
            if probe is None or force is None:
                continue
            point, normal, penetration = self._load_point(name, probe)
            if penetration <= -self.reach_m:
                continue
            push = float(force @ normal)
            if push > 0.0:
                user = self._users.get(name)
                rest_point, rest_normal = self._material(point, normal, user)
                keys.append(
                    self.obj.patch_key(
                        rest_point, user.key if user is not None else None, rest_normal
                    )
                )
                forces.append(push)
                pushed[name] = push
        self.obj.step(keys, forces)
        self._current = np.asarray(self.obj.vertices, dtype=np.float64)
        self._bound = float(self.obj.max_displacement_m)
        self._tick += 1
        if not names:
            self._users.clear()
            self.coupling = Coupling((), np.zeros((0, 0)), np.zeros(0), self.proximity_m)
            return {}

        # Step 1: every probe on the new surface.
        probes = [self._probe_for(name, inputs[name]) for name in names]
        located = [
            self._locate(probe, self._users.get(name))
            for name, probe in zip(names, probes, strict=True)
        ]
        patch_keys = []
        rest_planes: list[Plane | None] = []
        materials = [self._material_of(s) for s in located]
        for name, s, (rest_point, rest_normal) in zip(names, located, materials, strict=True):
            user = self._users.get(name)
            rest_planes.append(self._rest_plane(s, rest_point) if len(names) == 1 else None)
            # a probe in free space may keep a solved patch while its own is solved ahead
            # (PatchedSurface.patch_key): the tick never waits for a hand moving in the air
            free = s.penetration_m <= -self.proximity_m
            patch_keys.append(
                self.obj.patch_key(
                    rest_point, user.key if user is not None else None, rest_normal, free=free
                )
            )
        # Step 2 inputs: K_o, B_o and the coupling-aware K_o_eff.
        compliance = self.obj.contact_compliance(patch_keys)
        diag = np.diag(compliance)
        k_o = np.where(diag > 1.0 / K_O_MAX, 1.0 / np.maximum(diag, 1e-300), K_O_MAX)
        b_o = np.asarray(self.obj.contact_damping(patch_keys), dtype=np.float64)
        pen = np.array([s.penetration_m for s in located])
        near = np.flatnonzero(pen > -self.proximity_m)
        k_eff = k_o.copy()
        k_stiff = k_o.copy()
        if len(near):
            c_near = compliance[np.ix_(near, near)]
            k_eff[near] = effective_stiffness(c_near, k_o[near])
            k_stiff[near] = stiff_stiffness(c_near, k_o[near])

        number = self._tick if tick is None else int(tick)
        out: dict[str, SurfacePatch] = {}
        users: dict[str, _UserState] = {}
        for i, (name, s) in enumerate(zip(names, located, strict=True)):
            prim: Plane | Sphere
            if self.primitive == "sphere":
                prim = fit_sphere(
                    s, self._index, self._current, self.obj.patch_radius_m, self._bound
                )
            else:
                prim = fit_plane(s)
            users[name] = _UserState(
                probe=probes[i],
                primitive=prim,
                key=patch_keys[i],
                surface=s,
                rest_point=materials[i][0],
                rest_normal=materials[i][1],
            )
            out[name] = SurfacePatch(
                tick=number,
                primitive=prim,
                proxy=_t3(s.point),
                normal=_t3(s.normal),
                penetration_m=float(s.penetration_m),
                k_o=float(k_o[i]),
                k_o_eff=float(k_eff[i]),
                k_o_stiff=float(k_stiff[i]),
                b_o=float(b_o[i]),
                in_contact=bool(s.penetration_m > 0.0),
                own_force_n=pushed.get(name, 0.0),
                rest_plane=rest_planes[i],
            )
        self._users = users
        self.coupling = Coupling(tuple(names), compliance, pen, self.proximity_m)
        return out


def _t3(a: FloatArray) -> Vec3:
    """A (3,) array [m] as the surface patch's tuple of floats."""
    return (float(a[0]), float(a[1]), float(a[2]))
