"""Deformable objects: admittance models that take contact forces and return surface positions.

The paper's objects (section 6, Step 3) receive the last force each user rendered and return a
new surface after one simulation period N*T, and report each contact's stiffness K_o and damping
B_o (eq. 6-9). :class:`AdmittanceObject` is the small interface :class:`server.world.World`
needs; :class:`server.objects.balloon.Balloon` (DESIGN section 5) implements it, and any other
model (a tetrahedral FEM solid, say) must expose the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt

from haptic_collab.server.objects.balloon import Balloon, BalloonParams, LoadPatch
from haptic_collab.server.objects.mesh import MeshError, default_balloon, load_mesh, repair_mesh


class AdmittanceObject(Protocol):
    """What the simulation core needs from a deformable object (all SI units).

    Surface: ``rest_vertices`` (n, 3) [m], ``faces`` (m, 3) int, ``vertices`` (n, 3) [m]
    current, ``max_displacement_m`` bounding ``|vertices - rest_vertices|``.
    Contacts are identified by patch keys from :meth:`patch_key`. ``sim_period_s`` [s] is the
    period N*T of one :meth:`step`: the server's :class:`shared.rates.Rates` ``sim_period_s``
    (:class:`server.world.World` and :class:`server.room.Room` refuse rates that disagree).
    """

    @property
    def rest_vertices(self) -> npt.NDArray[np.float64]: ...

    @property
    def faces(self) -> npt.NDArray[np.int32]: ...

    @property
    def vertices(self) -> npt.NDArray[np.float64]: ...

    @property
    def n_vertices(self) -> int: ...

    @property
    def max_displacement_m(self) -> float: ...

    @property
    def sim_period_s(self) -> float: ...

    @property
    def patch_radius_m(self) -> float: ...

    def patch_key(
        self,
        point: npt.ArrayLike,
        previous: int | None = None,
        normal: npt.ArrayLike | None = None,
        free: bool = False,
    ) -> int: ...

    def step(self, keys: Sequence[int], forces_n: npt.ArrayLike) -> None: ...

    def contact_compliance(self, keys: Sequence[int]) -> npt.NDArray[np.float64]: ...

    def contact_damping(self, keys: Sequence[int]) -> npt.NDArray[np.float64]: ...


__all__ = [
    "AdmittanceObject",
    "Balloon",
    "BalloonParams",
    "LoadPatch",
    "MeshError",
    "default_balloon",
    "load_mesh",
    "repair_mesh",
]
