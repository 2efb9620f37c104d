"""The FEM solid's quadratic element assembled independently, by scikit-fem: P2 displacement with a
constant pressure on each element (P2/P0), the pressure condensed.

``K = a_mu(u, v) + lambda B^T M_0^-1 B`` with ``a_mu`` scikit-fem's ``linear_elasticity(0, mu)``
(the shear terms), ``B`` the mixed form ``integral q div(u) dV`` against the P0 pressure ``q``
and ``M_0`` its mass, diagonal (one pressure per element), the elements' volumes: the mixed
element of Malkus and Hughes (1978) that the solid's selective integration of the ``lambda``
term equals (``server.objects.fem_elements.p2_stiffness_matrix``). Written from the formulation, not from
the solid's code, so a test comparing the two checks the assembly.
"""

from __future__ import annotations

import scipy.sparse as sp


def p2p0_stiffness(basis, lam: float, mu: float) -> sp.csr_matrix:
    """``K`` (basis.N, basis.N) [N/m] on scikit-fem's vector P2 ``basis`` (``ElementVector(
    ElementTetP2())`` on a ``MeshTet``), in scikit-fem's own dof order; ``lam``, ``mu`` [Pa]."""
    import skfem
    from skfem.helpers import div
    from skfem.models.elasticity import linear_elasticity

    pressure = basis.with_element(skfem.ElementTetP0())

    @skfem.BilinearForm
    def divergence(u, q, w):
        return q * div(u)

    @skfem.BilinearForm
    def mass(p, q, w):
        return p * q

    b = skfem.asm(divergence, basis, pressure)  # (pressures, displacements)
    volumes = skfem.asm(mass, pressure).diagonal()
    shear = skfem.asm(linear_elasticity(0.0, mu), basis)
    return (shear + lam * (b.T @ sp.diags(1.0 / volumes) @ b)).tocsr()
