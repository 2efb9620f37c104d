"""Compute interaction forces: the local model's force on the probe (phase 2 of the servo tick).

CHAI3D's ``computeInteractionForces``, for the paper's local model (section 6, Step 2): the
primitive of the newest patch gives the penetration e [m] and the outward normal n at the probe
x_h; the local model L(z) (eq. 12, with the threshold of eq. 17-18;
:class:`shared.local_model.LocalModel`) turns e into a force magnitude f [N]; in contact a probe
damper adds B_h * u, u the filtered depth rate of the probe. The force on the user is f * n,
before the safety supervisor clamps and scales it (:mod:`client.safety`).

Patch hand-over (:meth:`LocalRenderer.hand_over`), between ticks:

- ``zoh``: the new surface replaces the old at once (eq. 1);
- ``foh``: the penetration slides linearly from the old surface's to the new one's over N =
  ``hold_ticks`` ticks, e(k) = e_old(k) + (e_new(k) - e_old(k)) * k / N, k = 1..N-1, then
  e_new (:mod:`shared.full_loop` analyses exactly this); a patch that arrives mid-slide (network
  jitter) slides on from the blend reached, rebased once the next probe position is known, so
  the force never steps;
- the LocalModel keeps its integral state; the gain change's force step (K_h and the damper's
  (B_h,old - B_h,new) * u) is carried off by the model's gain transfer
  (``set_gains(..., carry_n=...)``);
- a change of own-force compensation C_h in contact (out of contact, a rise of it) moves the
  rendered surface by (C_h,old - C_h,new) F_s at once, F_s the own force of the patch rendered
  last (the change of F_s since is the new design's to render): that step is added to the
  penetration and driven to zero over the same transfer time, so the surface recedes (or comes
  out) gradually, and the K_h step of its next decrement is carried off with the gains'. With
  ``foh`` the slide over the simulation period starts from the old surface with the new
  compensation, so it carries the surface's motion alone (carrying the change of C_h too, on top
  of the transfer force of the K_h step, it rendered 5.45 N for a held 3 N). Out of contact a
  slide that deepens the surface ends; one that holds it back holds it no further back than the
  probe has left (dropped, it would put the surface out at once, into a retreating probe; kept
  whole, a returning probe met the surface deep inside). A transfer *force* would not do: the
  compensated probe rests on the object's own surface, which is where the surface lands when the
  compensation is withdrawn, so the contact would end on the next tick and the transfer with it
  (measured in the two-user demo: a resting user's 0.28 N fell to 0.003 N in one tick when the
  other touched and the uncoupled gains were withdrawn).
- a change between the rest plane (a user alone: :mod:`shared.gains.rest_plane`) and the current
  surface in contact puts the probe at another depth at once (the surface a press deformed lies
  F / K_o inside the rest plane): the step between what the old patch renders next at the last
  probe position and what the new one would is added to the penetration and slid off over the
  transfer time, as one slide (the change of C_h in it; no first-order hold across it). Out of
  contact only a new surface further out slides, held back no further than the probe has left.

Difference equations, per servo period T, with the probe's backward difference
d = x_h(k) - x_h(k-1):

- depth rate along the inward normal: v_in = -(d . n) / T;
- damper's velocity filter (time constant :data:`shared.full_loop.DAMPER_FILTER_S`):
  u(k) = u(k-1) + a * (v_in - u(k-1)), a = T / (T + tau);
- f = max(0, L(z) e + B_h * u) in contact, L(z) e out of contact.

No clock, no thread, no device: time advances one servo period per :meth:`LocalRenderer.render`.
"""

from __future__ import annotations

import math

from haptic_collab.shared.full_loop import DAMPER_FILTER_S
from haptic_collab.shared.local_model import LocalModel, LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate
from haptic_collab.shared.primitives import Primitive, moved_out

_NAN = math.nan


class LocalRenderer:
    """The local model rendered at the probe, one servo period per :meth:`render`.

    Parameters
    ----------
    params : LocalModelParams
        Threshold, release time, contact type and period T of the local model (its gains are
        replaced by each patch's).
    own_force_limit_n : float
        The largest own force F_s [N] the compensation carries (default unlimited; the servo
        passes the device's peak force). ValueError if not > 0.

    Attributes
    ----------
    model : LocalModel
        The local model L(z) (its integral and threshold state, read by the telemetry).
    patch : LocalModelUpdate or None
        The local model update in use (None before the first).
    primitive : Plane or Sphere or None
        Its primitive (None before the first patch).
    k_h : float
        K_h [N/m] in use (0 before the first patch).
    i_gain : float
        I [N/(m*s)] in use.
    b_h : float
        Probe damper B_h [N*s/m] in use.
    own_gain : float
        Own-force compensation C_h [m/N] in use (:mod:`shared.full_loop`; the patch's primitive
        is already moved out by it).
    own_offset_m : float
        How far [m] the patch's primitive is moved out, C_h F_s: the object's surface lies that
        far inside the rendered one (telemetry ``own_offset_m``).

    Notes
    -----
    Read the attributes, never assign them: they change only through :meth:`hand_over`.
    """

    __slots__ = (
        "model",
        "patch",
        "primitive",
        "k_h",
        "i_gain",
        "b_h",
        "own_gain",
        "own_offset_m",
        "own_force_limit_n",
        "_inv_T",
        "_a_u",
        "_u",
        "_prim_old",
        "_hold_off",
        "_hold_comp",
        "_rebase",
        "_hold_i",
        "_hold_n",
        "_off",
        "_off_step",
        "_own_force_n",
        "_off_used",
        "_fs_rendered",
        "_rest",
        "_px",
        "_py",
        "_pz",
        "_e_base",
    )

    def __init__(self, params: LocalModelParams, own_force_limit_n: float = math.inf) -> None:
        if not own_force_limit_n > 0.0:
            raise ValueError(f"own_force_limit_n must be > 0, got {own_force_limit_n!r}")
        T = params.servo_period_s
        self.own_force_limit_n = float(own_force_limit_n)
        self.model = LocalModel(params)
        self.patch: LocalModelUpdate | None = None
        self.primitive: Primitive | None = None
        self.k_h = 0.0
        self.i_gain = 0.0
        self.b_h = 0.0
        self.own_gain = 0.0
        self.own_offset_m = 0.0
        self._inv_T = 1.0 / T
        self._a_u = T / (T + DAMPER_FILTER_S)  # the damper's velocity filter (shared.full_loop)
        self._u = 0.0
        self._prim_old: Primitive | None = None  # the surface a first-order hold moves away from
        self._hold_off = 0.0  # depth [m] added to _prim_old: where the slide really starts
        # depth [m] added to _prim_old for a change of C_h: the old surface with the new
        # compensation, so the slide carries the surface's motion alone (hand_over)
        self._hold_comp = 0.0
        # a patch that arrived mid-slide: (start surface, its offset, weight reached); the new
        # slide's start offset is computed from it on the next render, once the probe is read
        self._rebase: tuple[Primitive, float, float] | None = None
        self._hold_i = 0
        self._hold_n = 1
        self._off = 0.0  # depth [m] added to e after a change of C_h, driven to zero
        self._own_force_n = 0.0  # F_s [N] the last patch's compensation carried (capped)
        self._off_used = 0.0  # the slide's depth [m] in the last tick's penetration
        self._fs_rendered = 0.0  # F_s [N] of the patch the last tick rendered (capped)
        self._off_step = 0.0
        self._rest = False  # the patch in use renders the rest plane (shared.gains.rest_plane)
        # the probe [m] the last tick rendered at
        self._px = self._py = self._pz = 0.0
        self._e_base = 0.0  # that tick's penetration [m] before the slide's depth

    @property
    def damper_velocity_m_s(self) -> float:
        """The damper's filtered depth rate u [m/s] along the inward normal."""
        return self._u

    def hand_over(self, patch: LocalModelUpdate, fresh: bool) -> None:
        """Make ``patch`` the local model from the next :meth:`render` on.

        Parameters
        ----------
        patch : LocalModelUpdate
            The new primitive and gains (validated, and clamped to the device by
            :meth:`client.servo.ServoCore.set_patch`).
        fresh : bool
            No surface to slide from (after a link loss): the patch replaces the old one at once
            even with ``proxy_hold="foh"``. The first patch is always fresh.
        """
        fresh = fresh or self.primitive is None
        transfer = self.model.params.gain_transfer_s
        # a change between the rest plane and the current surface: the step between what the old
        # patch renders next at the probe and what the new one would is slid off over the transfer
        # time, in contact (out of contact only a new surface further out, held back no further
        # than the probe has left, as a rise of C_h below); no first-order hold across it
        switch_step: float | None = None
        if not fresh and transfer > 0.0 and patch.rest_plane != self._rest:
            new_prim = patch.primitive
            cap = self.own_force_limit_n
            if patch.own_gain > 0.0 and patch.own_force_n > cap:
                new_prim = moved_out(new_prim, -patch.own_gain * (patch.own_force_n - cap))
            step = self._e_base + self._off - new_prim.contact(self._px, self._py, self._pz)[0]
            if self.model.in_contact or step < 0.0:
                switch_step = step
        old = self._prim_old
        if fresh or patch.proxy_hold != "foh" or switch_step is not None:
            self._prim_old = None
            self._rebase = None
        else:
            # a patch arriving before the last slide finished (network jitter) slides on from
            # the blend reached, not from the last target (that would be a step)
            self._rebase = (
                None
                if old is None
                else (old, self._hold_off + self._hold_comp, self._hold_i / self._hold_n)
            )
            self._prim_old = self.primitive
            self._hold_off = 0.0
        self._hold_comp = 0.0
        self._hold_i = 0
        self._hold_n = patch.hold_ticks
        self.patch = patch
        self.primitive = patch.primitive
        # own-force compensation carries the whole own force up to the device's peak force (the
        # servo clamps there anyway). Capping it lower, at the continuous force as the integral
        # is capped, left the force beyond the cap to K_h against the object without
        # compensation: a loop the gain design does not check, unstable on a FEM torus that
        # rings near the simulation's Nyquist frequency (docs/own-force.md). Motor heating is
        # the thermal limit's (client/thermal.py), which lowers the force, not the compensation.
        cap = self.own_force_limit_n
        excess = patch.own_force_n - cap
        if patch.own_gain > 0.0 and excess > 0.0:
            self.primitive = moved_out(patch.primitive, -patch.own_gain * excess)
        # the damper's share of the force step is carried off with the stiffness's
        b_old = self.b_h
        carry = (b_old - patch.b_h) * self._u if b_old > 0.0 or patch.b_h > 0.0 else 0.0
        # and so is the K_h step of the slide's next decrement, already taken from _off: the
        # model's step is on the last tick's penetration (without it, designs 7 ticks apart
        # stepped a held 3 N by up to 0.2 N)
        carry += (self.k_h - patch.k_h) * (self._off - self._off_used)
        # a change of own-force compensation moved the surface by (C_old - C_new) F_s: it slides
        # there over the transfer time (module docstring), whatever the hold; out of contact only
        # a rise of C_h, which moves the surface out toward a probe that just left (render holds
        # it no further back than the probe). A first-order hold slides from the old surface with
        # the new compensation: its slide over the simulation period carried the change too, and
        # with the K_h step's transfer force on top the force rose by 80 % in one simulation
        # period, the probe still (C_h K_h = 1 at 580 and 67 N/m)
        if fresh or transfer <= 0.0:
            self._off = 0.0
        elif switch_step is not None:
            # the whole step, C_h's change in it; no decrement pending (the K_h step is on the
            # rendered penetration, which the slide keeps)
            self._off = switch_step
            self._off_used = switch_step
            self._off_step = switch_step * self.model.params.servo_period_s / transfer
        elif patch.own_gain != self.own_gain and (
            self.model.in_contact or patch.own_gain > self.own_gain
        ):
            # at the F_s of the patch the last tick rendered: the change of F_s since is the new
            # design's to render with its own hold and C_h (at the new F_s a zero-order hold
            # stepped by C_h,old dF_s whatever the new design: 0.21 N in one tick, a press into
            # the stiffening object), and patches handed over between two ticks add up to the
            # newest one alone (JS's worker hands over every queued patch: 8.9 N for 1.2)
            step = (self.own_gain - patch.own_gain) * self._fs_rendered
            self._off += step
            self._off_used += step  # not a decrement: a second patch before the next tick
            if self._prim_old is not None:
                self._hold_comp = -step
            # linearly to zero over the transfer time from now (patches without a change of
            # C_h leave the slide's rate alone)
            self._off_step = self._off * self.model.params.servo_period_s / transfer
        self.model.set_gains(
            patch.k_h,
            patch.i_gain,
            patch.recovery_m_per_n,
            carry_n=carry,
            drop_integral=patch.own_gain > 0.0,
        )
        self.k_h = patch.k_h
        self.i_gain = patch.i_gain
        self.b_h = patch.b_h
        self.own_gain = patch.own_gain
        self._own_force_n = min(patch.own_force_n, cap)
        self.own_offset_m = patch.own_gain * self._own_force_n
        self._rest = patch.rest_plane

    def render(
        self, x: float, y: float, z: float, dx: float, dy: float, dz: float
    ) -> tuple[float, float, float, float, float, bool]:
        """Advance one servo period with the probe at (x, y, z) [m], moved by (dx, dy, dz) [m].

        Parameters
        ----------
        x, y, z : float
            Probe position x_h [m], finite.
        dx, dy, dz : float
            Its change since the last tick [m] (zero on the first tick): the backward difference
            the depth rate and the damper use.

        Returns
        -------
        f : float
            Force magnitude [N] along the outward normal (local model plus damper; before the
            safety clamp and scale); the force vector is f * n. 0 before the first patch.
        e : float
            Penetration e [m] (blended during a first-order hold); NaN before the first patch.
        nx, ny, nz : float
            Outward unit normal n of the surface at the probe; zero before the first patch.
        in_contact : bool
            The local model is in contact.
        """
        prim = self.primitive
        if prim is None:
            return 0.0, _NAN, 0.0, 0.0, 0.0, False
        e, nx, ny, nz = prim.contact(x, y, z)
        old = self._prim_old
        if old is not None:  # first-order hold: slide from the old surface to the new one
            rb = self._rebase
            if rb is not None:  # start where the interrupted slide was: its blend, here
                s_prim, s_off, w = rb
                self._hold_off = (1.0 - w) * (
                    s_prim.contact(x, y, z)[0] + s_off - old.contact(x, y, z)[0]
                )
                self._rebase = None
            hi = self._hold_i + 1
            if hi >= self._hold_n:
                self._prim_old = None
            else:
                self._hold_i = hi
                e_old = old.contact(x, y, z)[0] + self._hold_off + self._hold_comp
                e = e_old + (e - e_old) * (hi / self._hold_n)
        off = self._off
        self._off_used = off
        self._fs_rendered = self._own_force_n
        self._px, self._py, self._pz = x, y, z  # plain stores: no tuple per tick
        self._e_base = e
        if off != 0.0:  # a change of C_h, sliding in (hand_over)
            e += off
            nxt = off - self._off_step
            self._off = nxt if (nxt > 0.0) == (off > 0.0) and nxt != 0.0 else 0.0
        # the probe's depth rate along the inward normal (backward difference, never the proxy's)
        v_in = -(dx * nx + dy * ny + dz * nz) * self._inv_T
        lm = self.model
        f = lm.step(e, v_in)
        in_contact = lm.in_contact
        if not in_contact and off != 0.0:
            # a slide that deepens the surface ends with the contact (as the model's transfer
            # force). One that holds it back (C_h rose) holds it back no further than the probe
            # has left: dropped, it put the surface out at once, into a retreating probe (3 N
            # held at 580 N/m handed to 67 N/m, retracted at 0.5 m/s: 2.53 N, 0, then 2.46 N
            # again); kept whole, a probe coming back met the surface 1.3-12.5 mm deep
            self._off = 0.0 if off > 0.0 else min(0.0, max(self._off, off - e))
        u = self._u + self._a_u * (v_in - self._u)
        self._u = u
        if in_contact:
            b_h = self.b_h
            if b_h > 0.0:
                f += b_h * u  # probe damper on the filtered probe velocity
                if f < 0.0:
                    f = 0.0
        return f, e, nx, ny, nz, in_contact

    def reset(self) -> None:
        """Forces withheld: forget the local model's integral and contact state (no wind-up).

        Does nothing before the first patch.
        """
        if self.primitive is not None:
            self.model.reset()
            self._off = 0.0
