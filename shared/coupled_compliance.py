"""The contacts' compliance matrix and its modal stiffnesses: the object block of M coupled users.

With M users on one object, the object's part of the coupled loop (:mod:`shared.coupled_loop`)
is the contacts' normal compliance ``C`` (M x M, [m/N], symmetric positive semi-definite,
DESIGN section 5, ``C_ij = beta_i^T K^-1 beta_j``): eq. 6 written for M contacts maps the M
sampled forces to the M surface displacements. This module builds the product's
parametrisation of ``C`` (:func:`compliance_matrix`: equal pairwise coupling ``c``), checks a
given one (:func:`check_compliance`), and reduces it to the per-contact stiffnesses the gain
design works with (:func:`modal_stiffness`). With ``S = K^1/2 C K^1/2`` (``K = diag(K_o,i)``,
``K_o,i = 1 / C_ii``, so S has a unit diagonal):

- ``K_o = 1 / C_ii``: the contact's own stiffness (paper eq. 6-8 for one contact);
- ``K_o_eff = K_o / lambda_max(S)``: the common mode, all users pressing together on a softer
  object (what the server reports, :func:`server.contact_stiffness.effective_stiffness`);
- ``K_o_stiff = K_o / lambda_min(S)``: the differential mode, one user pressing, another pushed
  back; capped at :data:`shared.gains.key.K_O_RIGID`.

For ``C = (1/K_o) ((1 - c) I + c 1 1^T)``: ``K_o_eff = K_o / (1 + (M-1) c)`` and
``K_o_stiff = K_o / (1 - c)``. Why a PI user needs the whole range between them is the modal
argument of :mod:`shared.coupled_loop`.

Units SI throughout.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from haptic_collab.shared.gains.key import K_O_RIGID
from haptic_collab.shared.types import FloatArray


def compliance_matrix(k_o: float | Sequence[float], coupling: float, users: int = 2) -> FloatArray:
    """The contacts' compliance with equal pairwise coupling, (M, M) [m/N].

    ``C_ii = 1 / K_o,i`` and ``C_ij = c / sqrt(K_o,i K_o,j)`` for i != j (the product's
    parametrisation: c is the cross compliance as a fraction of the diagonal, DESIGN section 5).

    Parameters
    ----------
    k_o : float or sequence of M floats
        Each contact's own stiffness K_o,i = 1 / C_ii [N/m], > 0.
    coupling : float
        c in [0, 1): 0 uncoupled contacts; about 0.9 for two contacts 2 cm apart on the default
        balloon (server.objects.balloon).
    users : int
        M >= 1 (ignored when ``k_o`` is a sequence).

    Raises
    ------
    ValueError
        Non-positive stiffness, c outside [0, 1), M < 1.
    """
    k = np.atleast_1d(np.asarray(k_o, dtype=float))
    if k.ndim != 1:
        raise ValueError(f"k_o must be a float or a 1-D sequence, got shape {k.shape}")
    if k.size == 1 and not isinstance(k_o, Sequence | np.ndarray):
        if int(users) < 1:
            raise ValueError(f"users must be >= 1, got {users!r}")
        k = np.full(int(users), float(k[0]))
    if k.size < 1 or not np.all(np.isfinite(k)) or np.any(k <= 0.0):
        raise ValueError(f"k_o must be finite stiffnesses > 0 N/m, got {k_o!r}")
    if not (math.isfinite(coupling) and 0.0 <= coupling < 1.0):
        raise ValueError(f"coupling must be in [0, 1), got {coupling!r}")
    s = 1.0 / np.sqrt(k)
    c = coupling * np.outer(s, s)
    np.fill_diagonal(c, 1.0 / k)
    return c


def check_compliance(compliance: ArrayLike) -> FloatArray:
    """The contacts' compliance checked and symmetrised, (M, M) [m/N].

    Parameters
    ----------
    compliance : (M, M) float [m/N]
        ``C_ij = beta_i^T K^-1 beta_j`` (DESIGN section 5; eq. 6 for M contacts): symmetric
        within round-off, positive semi-definite, positive diagonal.

    Returns
    -------
    (M, M) float64 [m/N]
        ``(C + C^T) / 2``.

    Raises
    ------
    ValueError
        Not square or empty, not finite, not symmetric, a diagonal entry <= 0 (a contact that
        cannot move), or not positive semi-definite.
    """
    c = np.asarray(compliance, dtype=float)
    if c.ndim != 2 or c.shape[0] != c.shape[1] or c.shape[0] < 1:
        raise ValueError(f"compliance must be a square (M, M) matrix, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("compliance must be finite")
    scale = float(np.max(np.abs(c)))
    if not np.allclose(c, c.T, rtol=0.0, atol=1e-12 * scale):
        raise ValueError("compliance must be symmetric")
    c = 0.5 * (c + c.T)
    if np.any(np.diag(c) <= 0.0):
        raise ValueError("compliance must have a positive diagonal (every contact can move)")
    d = 1.0 / np.sqrt(np.diag(c))
    if np.linalg.eigvalsh(d[:, None] * c * d[None, :])[0] < -1e-12:
        raise ValueError("compliance must be positive semi-definite")
    return c


@dataclass(frozen=True)
class ModalStiffness:
    """Per-contact stiffnesses of a compliance matrix (module docstring), each (M,) [N/m].

    Attributes
    ----------
    k_o : contact's own stiffness ``1 / C_ii``.
    k_o_eff : ``K_o / lambda_max(S)``, the softest mode seen at the contact (the server's K_o_eff).
    k_o_stiff : ``K_o / lambda_min(S)``, the stiffest mode, capped at :data:`K_O_RIGID`.
    """

    k_o: FloatArray
    k_o_eff: FloatArray
    k_o_stiff: FloatArray


def modal_stiffness(compliance: ArrayLike) -> ModalStiffness:
    """Softest and stiffest modal stiffness of the contacts (module docstring), SI units.

    Parameters
    ----------
    compliance : (M, M) float [m/N], symmetric positive semi-definite, positive diagonal

    Raises
    ------
    ValueError
        Not square, not finite, not symmetric, not PSD, or a zero diagonal entry.
    """
    c = check_compliance(compliance)
    k = 1.0 / np.diag(c)
    d = np.sqrt(k)
    lam = np.linalg.eigvalsh(d[:, None] * c * d[None, :])
    # S has a unit diagonal, so lambda_min <= 1 <= lambda_max; round-off must not move an
    # uncoupled contact off K_o
    hi = max(float(lam[-1]), 1.0)
    lo = min(float(lam[0]), 1.0)
    hi = 1.0 if hi - 1.0 < 1e-12 else hi
    lo = 1.0 if 1.0 - lo < 1e-12 else lo
    rigid = np.maximum(K_O_RIGID, k)
    stiff = np.minimum(k / lo, rigid) if lo > 0.0 else rigid
    return ModalStiffness(k_o=k, k_o_eff=k / hi, k_o_stiff=stiff)
