"""A FEM contact with slow modes, for the tests of the loop on a solid's modes: the default
sphere's shape (a cheaper mesh) in liver, with the presets' mass-proportional damping."""

from __future__ import annotations

from haptic_collab.server.objects.fem import FemParams, FemSolid
from haptic_collab.server.objects.mesh import default_balloon

#: Where a user touches the 0.1 m ball: a point on its surface and the outward normal there.
POINTS = {"side": ((0.1, 0.0, 0.0), (1.0, 0.0, 0.0)), "top": ((0.0, 0.0, 0.1), (0.0, 0.0, 1.0))}


def liver_ball(cache_dir: str) -> FemSolid:
    """The ball (its volume mesh cached in ``cache_dir``)."""
    return FemSolid(default_balloon(0.1, 2), FemParams(rayleigh_alpha=1.11), cache_dir=cache_dir)


def contact_key(solid: FemSolid, at: str) -> int:
    """The solid's key of a contact at ``at`` (``side`` or ``top``)."""
    point, normal = POINTS[at]
    return solid.patch_key(point, normal=normal)
