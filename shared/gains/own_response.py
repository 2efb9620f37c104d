"""How stiff is the object to this user's own force? (the own-response check)

The product's gain design holds on objects from 15 % softer than the K_o reported to 25 % stiffer
(:class:`shared.gains.key.GainKey`), because a reported K_o may be wrong (a nonlinear or
viscoelastic object, a stiffness estimated cheaply). That robustness is paid for in transparency
on an object whose K_o is right: a damper, or a K_h away from K_o, felt over the band
(docs/fidelity.md). This module measures, from what every patch already carries, whether the
object answers this user's own force as a spring, and of which stiffness K' (the K_o reported, or
another it identifies); only then may the client render the plane checked for a stiffness known
to within a few percent (:func:`shared.gains.verified_plane.verified_plane`).

Each patch gives the surface's depth along the contact normal ``x_s`` [m] (positive into the
object), the force the simulation applied from this user ``F_s`` [N] and the K_o reported [N/m].
The K_o reported is the object's tangent stiffness there, and may move as the object is pressed
(a strain-stiffening object: Fung's exponential law). The deformation it predicts, ``u``, adds up
each change of force over the K_o reported across it, ``du = dF_s / K_o``, with K_o taken to vary
linearly with the force between two patches, as it does on Fung's law (``K_t = k_1 + F / x_s``):
``du = dF_s ln(K_1 / K_0) / (K_1 - K_0)``, the change over the logarithmic mean of the two K_o
(:func:`update_deformation`); ``u = F_s / K_o`` at the first patch. On a spring, ``u = F_s /
K_o``. On an object whose tangent is ``K' / K_o`` times the one reported, pressed by this user
alone, ``x_s = r + u / rho`` with ``r`` the rest surface and ``rho = K' / K_o``. The rest surface
the reports imply, ``r_hat = x_s - u``, then moves with ``u`` by ``(1 / rho - 1) u``: a
least-squares line of ``r_hat`` against ``u``, weighted by ``exp(-age / window_s)``, has slope
``s`` and gives ``rho = 1 / (1 + s)`` (model-mediated teleoperation's estimate of the rest
surface, Mitra and Niemeyer 2008, turned into a check of the stiffness its plane needs). Forces
are read from ``u`` with the newest K_o reported (a spread of ``u`` of 1 mm on 300 N/m is 0.3 N).
Another user's push moves ``r_hat`` without this user's force and adds to the line's residual,
not its slope, as long as the two are not correlated; the client only runs the check on an
uncoupled contact.

The verdict (:attr:`OwnResponse.verified`) holds the object to a stiffness ``ref K_o``
(:attr:`OwnResponse.identified`, ``ref`` 1 at the start: the K_o reported):

- *verified* once the deformations ``u`` in the window spread by at least ``min_depth_spread_m``
  (standard deviation) or by what takes ``min_force_spread_n`` on the K_o reported, the line
  explains ``r_hat`` to within ``max_residual`` of that spread, and ``|rho / ref - 1| <=
  tolerance``;
- *refused* at once when ``|rho / ref - 1| > refuse_tolerance`` or the residual is too large,
  with the spread met, or when the newest patch lies off the line by more than
  ``refuse_tolerance u / ref`` (an object that changed under a held force); otherwise, without
  that spread (a held press), the last verdict stands. The client starts the check over (``ref``
  back to 1) when the contact ends;
- *identified* (:func:`identify`): once the check has read the contact for
  :data:`IDENTIFY_AFTER_S` and :data:`IDENTIFY_MIN_SAMPLES` patches, and no change of force
  between two patches carried more than :data:`IDENTIFY_MAX_JUMP_SHARE` of the force's movement
  (a line through two levels of force held apart by a jump, or by a few patches, says nothing of
  what lies between: a surface that moved with the jump, an object that changed;
  :func:`update_jumps`), where the spread is met and the
  line explains ``r_hat`` but ``rho`` is more than ``refuse_tolerance`` off ``ref``, and within :data:`IDENTIFY_RANGE` of
  the K_o reported, ``ref`` moves to ``rho`` and the object is verified as that stiffness (the
  K_o reported may be wrong: a stiffness estimated cheaply, a linearised FEM; model-mediated
  teleoperation renders the stiffness it estimates, Mitra and Niemeyer 2008). The hysteresis
  keeps ``ref`` where it is while ``rho`` stays within ``refuse_tolerance`` of it.

The state is a few weighted sums (:data:`SUMS`); :func:`update_sums` and :func:`verdict` work on
arrays of any shape, so a batch of contacts (the fidelity benchmark's simulator,
:mod:`haptic_collab.research.fidelity_1d`) runs the same arithmetic as one client. Pure: time is
passed in, no clocks, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from haptic_collab.shared.gains.policy import (
    IDENTIFY_AFTER_S,
    IDENTIFY_MAX_JUMP_SHARE,
    IDENTIFY_MIN_SAMPLES,
    IDENTIFY_RANGE,
    MAX_RESIDUAL,
    MIN_DEPTH_SPREAD_M,
    MIN_FORCE_SPREAD_N,
    REFUSE_TOLERANCE,
    TOLERANCE,
    WINDOW_S,
)
from haptic_collab.shared.types import FloatArray

#: The weighted sums the check keeps, in this order along the last axis: weight W, sum u, sum r,
#: sum u^2, sum u r, sum r^2 (u the deformation the K_o reported predicts [m], r the rest-surface
#: estimate [m]).
SUMS = 6
#: The deformation state the check keeps, in this order along the last axis: ``u`` [m], the last
#: force [N] and the last K_o reported [N/m] (:func:`update_deformation`).
DEFORMATION = 3

#: The jump sums the check keeps, in this order along the last axis: the largest ``dF^2``
#: [N^2], the sum of ``dF^2`` [N^2] (both aged by ``exp(-dt / window_s)``), the last force [N].
JUMPS = 3


def empty_jumps(shape: tuple[int, ...] = ()) -> FloatArray:
    """Jump sums of contacts of ``shape`` before their first patch: shape ``shape + (JUMPS,)``."""
    out = np.zeros((*shape, JUMPS))
    out[..., 2] = np.nan
    return out


def update_jumps(
    jumps: FloatArray,
    *,
    dt_s: float | FloatArray,
    force_n: float | FloatArray,
    window_s: float = WINDOW_S,
) -> FloatArray:
    """The jump sums (:data:`JUMPS`) after one patch of force ``force_n`` [N], ``dt_s`` [s]
    after the last; shape as ``jumps``. Where the force is not finite the contact's sums are
    returned unchanged (the next finite force is compared with the last finite one)."""
    f = np.asarray(force_n, dtype=float)
    a = np.exp(-np.asarray(dt_s, dtype=float) / window_s)
    d2 = np.square(f - jumps[..., 2])
    d2 = np.where(np.isfinite(d2), d2, 0.0)
    out = np.stack(
        np.broadcast_arrays(np.maximum(jumps[..., 0] * a, d2), jumps[..., 1] * a + d2, f),
        axis=-1,
    )
    ok = np.isfinite(f) & np.isfinite(a)
    return np.where(np.asarray(ok)[..., None], out, jumps)


def jump_share(jumps: FloatArray) -> FloatArray:
    """The largest change of force's share of the movement (:func:`update_jumps`), shape
    ``jumps.shape[:-1]``: 1 where the force never moved."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(jumps[..., 1] > 0.0, jumps[..., 0] / jumps[..., 1], 1.0)


def empty_sums(shape: tuple[int, ...] = ()) -> FloatArray:
    """Zeroed sums for contacts of ``shape``: shape ``shape + (SUMS,)``."""
    return np.zeros((*shape, SUMS))


def empty_deformation(shape: tuple[int, ...] = ()) -> FloatArray:
    """Deformation state of contacts of ``shape`` before their first patch: shape ``shape +
    (DEFORMATION,)``."""
    out = np.full((*shape, DEFORMATION), np.nan)
    out[..., 0] = 0.0
    return out


def update_deformation(
    state: FloatArray,
    *,
    force_n: float | FloatArray,
    k_o: float | FloatArray,
) -> FloatArray:
    """The deformation state (:data:`DEFORMATION`) after one patch of force ``force_n`` [N]
    with the K_o reported ``k_o`` [N/m] > 0; shape as ``state``. ``u`` grows by the change of
    force over the logarithmic mean of the last K_o and this one (the module docstring: exact
    where the tangent stiffness is linear in the force, as on Fung's exponential law; ``dF /
    K_o`` where K_o did not change), and is ``F / K_o`` at the first patch. Where an input is not
    finite the contact's state is returned unchanged.
    """
    f = np.asarray(force_n, dtype=float)
    k = np.asarray(k_o, dtype=float)
    f0, k0 = state[..., 1], state[..., 2]
    first = ~(np.isfinite(f0) & np.isfinite(k0))
    with np.errstate(invalid="ignore", divide="ignore"):
        dk = k - k0
        # the logarithmic mean of k0 and k; k itself where they (nearly) agree
        lm = np.where(np.abs(dk) > 1e-9 * k, dk / np.log(k / k0), k)
        u = np.where(first, f / k, state[..., 0] + (f - f0) / lm)
    out = np.stack(np.broadcast_arrays(u, f, k), axis=-1)
    ok = np.isfinite(out).all(axis=-1) & (k > 0.0)
    return np.where(np.asarray(ok)[..., None], out, state)


def update_sums(
    sums: FloatArray,
    *,
    dt_s: float | FloatArray,
    surface_m: float | FloatArray,
    deformation_m: float | FloatArray,
    window_s: float = WINDOW_S,
) -> FloatArray:
    """The sums after one patch: the old ones aged by ``dt_s`` [s] (the time since the last
    patch), plus this patch's ``(u, r_hat = x_s - u)``; shape as ``sums``.

    ``surface_m``: the surface's depth along the contact normal [m]; ``deformation_m``: the
    deformation ``u`` the K_o reported predicts for the force the simulation applied from this
    user [m] (:func:`update_deformation`; ``F_s / K_o`` on a spring). Where an input is not
    finite the contact's sums are returned unchanged.
    """
    u = np.asarray(deformation_m, dtype=float)
    r = np.asarray(surface_m, dtype=float) - u
    a = np.exp(-np.asarray(dt_s, dtype=float) / window_s)
    new = np.stack(np.broadcast_arrays(np.ones_like(r), u, r, u * u, u * r, r * r), axis=-1)
    out = sums * np.asarray(a)[..., None] + new
    ok = np.isfinite(new).all(axis=-1) & np.isfinite(a)
    return np.where(ok[..., None], out, sums)


def fit(sums: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(slope, spread, residual)`` of the weighted line ``r_hat = a + s u``: ``s`` (no unit),
    the weighted standard deviation of ``u`` [m] and the rms residual [m], each of shape
    ``sums.shape[:-1]``; NaN where the window holds fewer than two distinct ``u``."""
    w = sums[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        mu, mr = sums[..., 1] / w, sums[..., 2] / w
        vuu = np.maximum(sums[..., 3] / w - mu * mu, 0.0)
        vur = sums[..., 4] / w - mu * mr
        vrr = np.maximum(sums[..., 5] / w - mr * mr, 0.0)
        s = np.where(vuu > 0.0, vur / vuu, np.nan)
        res = np.sqrt(np.maximum(vrr - np.where(vuu > 0.0, vur * s, np.nan), 0.0))
    return s, np.sqrt(vuu), res


def _reading(
    sums: FloatArray,
    k: FloatArray,
    min_force_spread_n: float,
    min_depth_spread_m: float,
    max_residual: float,
) -> tuple[FloatArray, FloatArray, np.ndarray, np.ndarray]:
    """What the window shows, shape ``sums.shape[:-1]`` each: the line's slope, ``rho``,
    whether the spread is met (``k`` the K_o reported reads it as a force), and whether the line
    explains ``r_hat`` (the module's rules; :func:`verdict` and :func:`identify` read the same)."""
    s, spread, res = fit(sums)
    rho = _slope_ratio(s)
    with np.errstate(invalid="ignore", divide="ignore"):
        shown = (spread * k >= min_force_spread_n) | (spread >= min_depth_spread_m)
        line = res <= max_residual * spread
    return s, rho, shown, line


def ratio(sums: FloatArray) -> FloatArray:
    """``rho = K' / K_o`` the window shows (NaN where it cannot tell, inf where the object showed
    no stiffness at all), shape ``sums.shape[:-1]``."""
    return _slope_ratio(fit(sums)[0])


def _slope_ratio(s: FloatArray) -> FloatArray:
    """``rho = 1 / (1 + s)`` of the line's slope ``s`` (:func:`ratio`)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        d = 1.0 + s
        return np.where(d > 0.0, 1.0 / d, np.where(np.isnan(d), np.nan, np.inf))


def verdict(
    sums: FloatArray,
    k_o: float | FloatArray,
    last: bool | np.ndarray,
    *,
    ref: float | FloatArray = 1.0,
    newest: tuple[float | FloatArray, float | FloatArray] | None = None,
    tolerance: float = TOLERANCE,
    refuse_tolerance: float = REFUSE_TOLERANCE,
    min_force_spread_n: float = MIN_FORCE_SPREAD_N,
    min_depth_spread_m: float = MIN_DEPTH_SPREAD_M,
    max_residual: float = MAX_RESIDUAL,
) -> np.ndarray:
    """Verified (bool, shape ``sums.shape[:-1]``): is the object the spring of ``ref`` times
    the K_o reported (default 1: K_o itself)? The module's rules, ``last`` the verdict so far.
    With ``newest`` = (``u`` [m], surface depth [m]) of the patch just added, the verdict is also
    withdrawn when that patch's ``r_hat`` is off the window's line by more than
    ``refuse_tolerance u / ref``: an object that changed under a held force (no spread to read
    a new slope from) shows there first."""
    k = np.asarray(k_o, dtype=float)
    ref_a = np.asarray(ref, dtype=float)
    s, rho, shown, line = _reading(sums, k, min_force_spread_n, min_depth_spread_m, max_residual)
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.abs(rho / ref_a - 1.0)
        good = shown & line & (off <= tolerance)
        bad = shown & (~line | ~(off <= refuse_tolerance))
        if newest is not None:
            u = np.asarray(newest[0], dtype=float)
            r = np.asarray(newest[1], dtype=float) - u
            w = sums[..., 0]
            mu, mr = sums[..., 1] / w, sums[..., 2] / w
            fitted = mr + np.where(np.isfinite(s), s, 0.0) * (u - mu)
            bad = bad | (np.abs(r - fitted) > refuse_tolerance * u / ref_a)
    return np.where(good & ~bad, True, np.where(bad, False, np.asarray(last, dtype=bool)))


def identify(
    sums: FloatArray,
    k_o: float | FloatArray,
    last: bool | np.ndarray,
    ref: float | FloatArray,
    *,
    elapsed_s: float | FloatArray = math.inf,
    jumps: FloatArray | None = None,
    newest: tuple[float | FloatArray, float | FloatArray] | None = None,
    identify_range: float = IDENTIFY_RANGE,
    identify_after_s: float = IDENTIFY_AFTER_S,
    identify_min_samples: float = IDENTIFY_MIN_SAMPLES,
    identify_max_jump_share: float = IDENTIFY_MAX_JUMP_SHARE,
    tolerance: float = TOLERANCE,
    refuse_tolerance: float = REFUSE_TOLERANCE,
    min_force_spread_n: float = MIN_FORCE_SPREAD_N,
    min_depth_spread_m: float = MIN_DEPTH_SPREAD_M,
    max_residual: float = MAX_RESIDUAL,
) -> tuple[np.ndarray, FloatArray]:
    """``(verified, ref)``, each of shape ``sums.shape[:-1]``: :func:`verdict` against ``ref``
    (K' / K_o the check holds the object to so far), except where the check has read the contact
    for ``elapsed_s`` [s] >= ``identify_after_s`` (to a nanosecond) and a weight of
    ``identify_min_samples`` patches, the largest change of force between two patches carries
    at most ``identify_max_jump_share`` of the force's movement (``jumps``:
    :func:`update_jumps`; None: not asked), and the window shows a line (spread met, residual
    small) whose ``rho`` is more than ``refuse_tolerance`` off ``ref`` and within
    ``identify_range`` of 1 (``1 / identify_range <= rho <= identify_range``): there ``ref``
    becomes ``rho`` and the verdict is :func:`verdict` against it (the module docstring's
    *identified*; the newest patch must lie on the line as always).

    Raises
    ------
    ValueError
        ``identify_range`` not finite and >= 1.
    """
    if not (math.isfinite(identify_range) and identify_range >= 1.0):
        raise ValueError(f"identify_range must be finite and >= 1, got {identify_range!r}")
    k = np.asarray(k_o, dtype=float)
    ref_a = np.broadcast_to(np.asarray(ref, dtype=float), sums.shape[:-1])
    _, rho, shown, line = _reading(sums, k, min_force_spread_n, min_depth_spread_m, max_residual)
    with np.errstate(invalid="ignore", divide="ignore"):
        moved = shown & line & (np.abs(rho / ref_a - 1.0) > refuse_tolerance)
        moved &= (rho >= 1.0 / identify_range) & (rho <= identify_range)
        moved &= np.asarray(elapsed_s, dtype=float) >= identify_after_s - 1e-9
        moved &= sums[..., 0] >= identify_min_samples
        if jumps is not None:
            moved &= jump_share(jumps) <= identify_max_jump_share
    new_ref = np.where(moved, rho, ref_a)
    ok = verdict(
        sums,
        k,
        np.where(moved, False, last),
        ref=new_ref,
        newest=newest,
        tolerance=tolerance,
        refuse_tolerance=refuse_tolerance,
        min_force_spread_n=min_force_spread_n,
        min_depth_spread_m=min_depth_spread_m,
        max_residual=max_residual,
    )
    return ok, new_ref


@dataclass
class OwnResponse:
    """The own-response check of one contact (module docstring).

    Call :meth:`update` with each patch of the contact, :meth:`reset` when the contact ends,
    becomes coupled to another user's, or the object reports a B_o > 0 (a viscoelastic
    object's response depends on how fast it is pressed, which the K_o and B_o reported do not
    say: the check does not read it). A K_o reported that moves as the object is pressed (a stiffening object) is read as its tangent
    (:func:`update_deformation`): the check goes on across gain-table cells.

    Raises
    ------
    ValueError
        Non-positive or non-finite parameters.
    """

    window_s: float = WINDOW_S
    tolerance: float = TOLERANCE
    refuse_tolerance: float = REFUSE_TOLERANCE
    min_force_spread_n: float = MIN_FORCE_SPREAD_N
    min_depth_spread_m: float = MIN_DEPTH_SPREAD_M
    max_residual: float = MAX_RESIDUAL
    identify_range: float = IDENTIFY_RANGE
    sums: FloatArray = field(default_factory=empty_sums, repr=False)
    verified: bool = False
    k_o: float = math.nan
    identify_after_s: float = IDENTIFY_AFTER_S
    identify_min_samples: float = IDENTIFY_MIN_SAMPLES
    identify_max_jump_share: float = IDENTIFY_MAX_JUMP_SHARE
    #: K' / K_o the verdict holds the object to (1: the K_o reported; :func:`identify`).
    identified_ratio: float = 1.0
    #: Time [s] the check has read the contact since it started (the patches' dt summed).
    elapsed_s: float = 0.0
    #: The changes of force between its patches (:func:`update_jumps`).
    jumps: FloatArray = field(default_factory=empty_jumps, repr=False)
    #: The deformation the K_o reported predicts (:func:`update_deformation`).
    deformation: FloatArray = field(default_factory=empty_deformation, repr=False)

    def __post_init__(self) -> None:
        for name in (
            "window_s",
            "tolerance",
            "refuse_tolerance",
            "min_force_spread_n",
            "min_depth_spread_m",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if not (math.isfinite(self.max_residual) and self.max_residual > 0.0):
            raise ValueError(f"max_residual must be finite and > 0, got {self.max_residual!r}")
        if self.refuse_tolerance < self.tolerance:
            raise ValueError("refuse_tolerance must be at least tolerance")
        for name in ("identify_min_samples", "identify_max_jump_share"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if not (math.isfinite(self.identify_after_s) and self.identify_after_s >= 0.0):
            raise ValueError(
                f"identify_after_s must be finite and >= 0, got {self.identify_after_s!r}"
            )
        if not (math.isfinite(self.identify_range) and self.identify_range >= 1.0):
            raise ValueError(f"identify_range must be finite and >= 1, got {self.identify_range!r}")

    def reset(self) -> None:
        """Forget the window, the verdict and the stiffness identified."""
        self.sums = empty_sums()
        self.verified = False
        self.k_o = math.nan
        self.identified_ratio = 1.0
        self.elapsed_s = 0.0
        self.jumps = empty_jumps()
        self.deformation = empty_deformation()

    def update(
        self,
        *,
        dt_s: float,
        surface_m: float,
        force_n: float,
        k_o: float,
    ) -> bool:
        """Add one patch (:func:`update_deformation`, :func:`update_sums`) and return the
        verdict (:func:`identify`): the object yields as a tangent of :attr:`identified` [N/m]
        to within ``tolerance``.

        Raises
        ------
        ValueError
            ``dt_s`` negative or ``k_o`` not a finite stiffness > 0 N/m (the sums are unchanged).
        """
        if not (math.isfinite(dt_s) and dt_s >= 0.0):
            raise ValueError(f"dt_s must be finite and >= 0 s, got {dt_s!r}")
        if not (math.isfinite(k_o) and k_o > 0.0):
            raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {k_o!r}")
        self.deformation = update_deformation(self.deformation, force_n=force_n, k_o=k_o)
        u = float(self.deformation[0]) if math.isfinite(force_n) else math.nan
        self.sums = update_sums(
            self.sums, dt_s=dt_s, surface_m=surface_m, deformation_m=u, window_s=self.window_s
        )
        self.k_o = float(k_o)
        self.elapsed_s += dt_s
        self.jumps = update_jumps(self.jumps, dt_s=dt_s, force_n=force_n, window_s=self.window_s)
        ok, ref = identify(
            self.sums,
            k_o,
            self.verified,
            self.identified_ratio,
            elapsed_s=self.elapsed_s,
            jumps=self.jumps,
            newest=(u, surface_m),
            identify_range=self.identify_range,
            identify_after_s=self.identify_after_s,
            identify_min_samples=self.identify_min_samples,
            identify_max_jump_share=self.identify_max_jump_share,
            tolerance=self.tolerance,
            refuse_tolerance=self.refuse_tolerance,
            min_force_spread_n=self.min_force_spread_n,
            min_depth_spread_m=self.min_depth_spread_m,
            max_residual=self.max_residual,
        )
        self.verified = bool(ok)
        self.identified_ratio = float(ref)
        return self.verified

    @property
    def ratio(self) -> float:
        """``rho = K' / K_o`` the window shows (NaN: it cannot tell yet)."""
        return float(ratio(self.sums)) if math.isfinite(self.k_o) else math.nan

    @property
    def identified(self) -> float:
        """The stiffness [N/m] the verdict holds the object to: :attr:`identified_ratio` times
        the latest K_o reported (NaN before the first patch)."""
        return self.identified_ratio * self.k_o
