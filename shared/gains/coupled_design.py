"""Gains for several users on one object, designed per user and verified on the coupled loop.

The design step of :mod:`shared.coupled_loop` (whose docstring has the modal argument): with M
users coupled through the object's compliance ``C``, a PI local model designed for the softest
modal stiffness ``K_o_eff`` alone can make the coupled loop unstable, because the differential
mode is much stiffer. :func:`design_coupled` therefore has each user design
(:func:`shared.gains.design.design_gains`) over its whole modal range
``[(1 - margin) K_o_eff, K_o_stiff]`` (:func:`shared.coupled_compliance.modal_stiffness`),
verifies the result on the coupled loop with different hands and sampling ticks per user
(:func:`shared.coupled_loop.verify_coupled`, against the single-user margin), and retunes to a
softer design stiffness until it passes; :class:`CoupledDesign` is the outcome.

Units SI throughout. This module reads no clock (``design_ms`` is set by the caller).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from haptic_collab.shared.checks import whole as _whole
from haptic_collab.shared.coupled_compliance import (
    ModalStiffness,
    check_compliance,
    modal_stiffness,
)
from haptic_collab.shared.coupled_loop import (
    CoupledVerdict,
    UserGains,
    verification_hands,
    verify_coupled,
)
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX, HandBox, ProxyHold
from haptic_collab.shared.gains.design import GainDesign, design_gains
from haptic_collab.shared.gains.key import Mode
from haptic_collab.shared.gains.policy import MIN_DECAY_RATE_PER_S


@dataclass(frozen=True)
class CoupledDesign:
    """Per-user gains for M coupled contacts, verified on the coupled loop (SI units).

    Attributes
    ----------
    designs : tuple of M GainDesign
        Each user's single-user design (:func:`shared.gains.design.design_gains`), made for
        ``k_o = design_k_o[u]`` and checked up to ``k_o_hi = modal.k_o_stiff[u]``.
    gains : tuple of M UserGains
        The same gains, ready for :func:`shared.coupled_loop.coupled_monodromy`.
    modal : ModalStiffness
        K_o, K_o_eff and K_o_stiff of every contact.
    design_k_o : tuple of M floats
        The stiffness [N/m] each user designed for: ``K_o_eff * retune**rounds``.
    verdict : CoupledVerdict
        The coupled loop's worst case (:func:`shared.coupled_loop.verify_coupled`).
    rounds : int
        Retuning rounds taken (0: the modal-range design met the margin at once).
    design_ms : float
        Wall time [ms] (informative), set by whoever ran the design and measured it (this module
        reads no clock); 0 when not measured.
    """

    designs: tuple[GainDesign, ...]
    gains: tuple[UserGains, ...]
    modal: ModalStiffness
    design_k_o: tuple[float, ...]
    verdict: CoupledVerdict
    rounds: int
    design_ms: float = 0.0

    def to_json(self) -> dict[str, object]:
        """Plain JSON-able dict."""
        return {
            "users": [d.to_json() for d in self.designs],
            "k_o": self.modal.k_o.tolist(),
            "k_o_eff": self.modal.k_o_eff.tolist(),
            "k_o_stiff": self.modal.k_o_stiff.tolist(),
            "design_k_o": list(self.design_k_o),
            "verdict": self.verdict.to_json(),
            "rounds": self.rounds,
            "design_ms": self.design_ms,
        }


def design_coupled(
    compliance: ArrayLike,
    *,
    b_o: ArrayLike = 0.0,
    servo_rate_hz: float = 1000.0,
    sim_rate_hz: float = 20.0,
    delay_ticks: int = 0,
    mode: Mode = "pi",
    margin: float = 0.15,
    k_h_max: float = math.inf,
    b_h_max: float = 0.0,
    holds: Sequence[ProxyHold] = ("zoh", "foh"),
    hand_box: HandBox = DEFAULT_HAND_BOX,
    retune: float = 0.85,
    max_rounds: int = 4,
    sample_ticks: Sequence[int] | None = None,
    min_decay_rate_per_s: float = MIN_DECAY_RATE_PER_S,
) -> CoupledDesign:
    """Gains for M users coupled through C with the same margin as one user (modal argument:
    :mod:`shared.coupled_loop`).

    1. Each user u designs (:func:`shared.gains.design.design_gains`) for its softest modal
       stiffness ``K_o_eff,u`` with the usual ``margin`` below it, *and* up to its stiffest modal
       stiffness ``K_o_stiff,u`` (``k_o_hi``): for identical users this covers every mode of the
       coupled loop exactly (modal decomposition).
    2. The coupled loop is verified (:func:`shared.coupled_loop.verify_coupled`) with every user
       taking every hand of :func:`shared.coupled_loop.verification_hands` and its own sampling
       tick, C as given and scaled by ``1 / (1 - margin)``, against the single-user
       ``rho_limit``.
    3. If it fails, every user re-designs for ``K_o_eff * retune**r`` (r = 1, 2, ...: a softer
       object, hence lower gains) up to ``max_rounds``.

    Parameters
    ----------
    compliance : (M, M) float [m/N]
        The contacts' normal compliance (symmetric PSD, positive diagonal).
    b_o : float or (M,) [N/m]
        Object damping per contact (eq. 9).
    servo_rate_hz, sim_rate_hz, delay_ticks, mode, margin, k_h_max, b_h_max, holds, hand_box,
    min_decay_rate_per_s
        As :func:`shared.gains.design.design_gains` (the same for every user).
    retune : float
        Factor in (0, 1) by which the design stiffness drops per retuning round.
    max_rounds : int
        Retuning rounds allowed, >= 0.
    sample_ticks : sequence of int, optional
        Per-user sampling ticks verified (default ``{0, N/2, N-1}``).

    Returns
    -------
    CoupledDesign
        The first design meeting the margin; if none does within ``max_rounds``, the one with the
        smallest coupled margin radius, with ``verdict.meets_margin`` False (the caller decides:
        the numbers say by how much).

    Raises
    ------
    ValueError
        Bad compliance or parameters, or as :func:`shared.gains.design.design_gains` (no local
        model stable over the hand box for some user).
    """
    c = check_compliance(compliance)
    m = c.shape[0]
    bo = np.broadcast_to(np.asarray(b_o, dtype=float), (m,)).copy()
    if not (math.isfinite(retune) and 0.0 < retune < 1.0):
        raise ValueError(f"retune must be in (0, 1), got {retune!r}")
    _whole("max_rounds", max_rounds, 0)
    modal = modal_stiffness(c)
    cache: dict[tuple[float, float, float], GainDesign] = {}
    best: CoupledDesign | None = None
    for r in range(int(max_rounds) + 1):
        k_design = tuple(float(k) * retune**r for k in modal.k_o_eff)
        designs = []
        for u in range(m):
            key = (k_design[u], float(modal.k_o_stiff[u]), float(bo[u]))
            if key not in cache:
                cache[key] = design_gains(
                    key[0],
                    b_o=key[2],
                    servo_rate_hz=servo_rate_hz,
                    sim_rate_hz=sim_rate_hz,
                    delay_ticks=delay_ticks,
                    mode=mode,
                    margin=margin,
                    k_o_hi=key[1],
                    k_h_max=k_h_max,
                    b_h_max=b_h_max,
                    holds=holds,
                    hand_box=hand_box,
                    min_decay_rate_per_s=min_decay_rate_per_s,
                )
            designs.append(cache[key])
        gains = tuple(UserGains.from_design(d) for d in designs)
        verdict = verify_coupled(
            c,
            gains,
            b_o=bo,
            servo_rate_hz=servo_rate_hz,
            sim_rate_hz=sim_rate_hz,
            delay_ticks=delay_ticks,
            margin=margin,
            hands=verification_hands(hand_box),
            sample_ticks=sample_ticks,
            min_decay_rate_per_s=min_decay_rate_per_s,
        )
        cand = CoupledDesign(
            designs=tuple(designs),
            gains=gains,
            modal=modal,
            design_k_o=k_design,
            verdict=verdict,
            rounds=r,
        )
        if best is None or verdict.margin_radius < best.verdict.margin_radius:
            best = cand
        if verdict.meets_margin:
            best = cand
            break
    assert best is not None
    return best
