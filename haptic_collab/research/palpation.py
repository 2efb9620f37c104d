"""Palpation: is a lump inside the FEM liver felt through its surface? (docs/palpation.md)

A user palpating presses the surface to a depth and slides; over a stiff lump the surface
pushes back harder at the same depth. What the hand compares is the contact stiffness under the
finger pad, ``K_o`` (:meth:`server.objects.fem.FemSolid.contact_stiffness`): at equal depth
``d`` the force is ``K_o d`` (the solid is linear), so the force over the lump over the force
beside it is ``K_o(over) / K_o(beside)``. The lump is felt when that ratio exceeds one stiffness
JND (10 %: :data:`haptic_collab.demo_report.STIFFNESS_JND`; the Weber fractions measured for
stiffness are 15-23 %, docs/fidelity.md).

The set-up (:func:`measure`): the FEM object of ``haptic server --object fem`` (the default
sphere, radius 0.1 m, liver) with a spherical lump (:func:`sphere_lump`) of diameter ``D`` whose
top is ``depth`` below the surface, under the surface point ``angle`` (20 degrees) from the top
in the x-z plane. *Beside* is the mirror point at ``-angle``: the same distance from the fixed
base, on the same mesh. The same mesh with one material is the control (its over/beside ratio
is the mesh's own asymmetry, a few tenths of a per cent).

``K_o`` with the lump is the solid's own (:class:`~server.objects.fem.FemSolid` with per-element
materials, :func:`server.objects.inclusions.element_materials`), so this measures what the
server sends.

Run ``python -m haptic_collab.research.palpation --out docs/results/palpation-DATE.json``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from haptic_collab.demo_report import STIFFNESS_JND
from haptic_collab.server.objects.fem import FemParams, FemSolid, sphere_for_solid
from haptic_collab.server.objects.inclusions import (
    ElementMaterials,
    Inclusion,
    element_materials,
    volume_with_inclusions,
)
from haptic_collab.server.objects.volume import TETGEN_SWITCHES
from haptic_collab.server.solid_materials import SOLID_PRESETS, SolidMaterial, solid_to_params
from haptic_collab.shared.types import FloatArray

#: The lump's polar angle from the top of the sphere [rad]: off the axis, so that its mirror
#: point is an equal place beside it.
LUMP_ANGLE_RAD = math.radians(20.0)

#: Icosphere subdivisions of the lump's surface (42 vertices, edges about 0.3 of its
#: diameter): the solid's quadratic (P2) elements resolve a lump this coarse, and a finer one
#: refines the volume mesh around it until the start-up costs minutes (docs/palpation.md).
LUMP_SUBDIVISIONS = 1


def lump_direction(angle_rad: float = LUMP_ANGLE_RAD, side: float = 1.0) -> FloatArray:
    """The unit vector (3,) from the sphere's centre to the surface point over the lump
    (``side`` +1) or beside it (-1, the mirror point): ``(side sin a, 0, cos a)``."""
    return np.array([side * math.sin(angle_rad), 0.0, math.cos(angle_rad)])


def sphere_lump(
    diameter_m: float,
    depth_m: float,
    solid_radius_m: float = 0.1,
    angle_rad: float = LUMP_ANGLE_RAD,
    subdivisions: int = LUMP_SUBDIVISIONS,
    side: float = 1.0,
) -> trimesh.Trimesh:
    """A spherical lump of ``diameter_m`` [m] whose top is ``depth_m`` [m] under the surface of a
    sphere of ``solid_radius_m`` [m] centred at the origin, on :func:`lump_direction` (``side``
    -1: its mirror image, where the twin of :func:`measure` goes).

    The lump is an icosphere of ``subdivisions`` scaled to the ball's volume: an inscribed
    42-vertex icosphere holds 87 % of it, so unscaled it would be a smaller lump than asked.

    Raises
    ------
    ValueError
        A diameter or depth not finite and > 0, or a lump that does not fit inside.
    """
    d, h, r = float(diameter_m), float(depth_m), float(solid_radius_m)
    if not (math.isfinite(d) and d > 0.0 and math.isfinite(h) and h > 0.0):
        raise ValueError(f"diameter and depth must be > 0 m, got {diameter_m!r}, {depth_m!r}")
    if h + d >= r:
        raise ValueError(f"a lump {d * 1e3:g} mm across {h * 1e3:g} mm deep does not fit")
    lump = trimesh.creation.icosphere(subdivisions=subdivisions, radius=d / 2.0)
    lump.apply_scale((math.pi * d**3 / 6.0 / float(lump.volume)) ** (1.0 / 3.0))
    lump.apply_translation(lump_direction(angle_rad, side) * (r - h - d / 2.0))
    return lump


@dataclass(frozen=True)
class PalpationResult:
    """One lump felt or not. Stiffnesses [N/m]; ``over`` the patch over the lump, ``beside``
    the mirror patch over its twin (module docstring); ``*_without``: the same mesh and patches
    with one material."""

    diameter_m: float
    depth_m: float
    factor: float
    k_o_over: float
    k_o_beside: float
    k_o_over_without: float
    k_o_beside_without: float
    lump_tets: int
    nodes: int

    @property
    def rise(self) -> float:
        """How much stiffer the surface over the lump is than beside it [1]: what the hand
        compares at equal depth."""
        return self.k_o_over / self.k_o_beside - 1.0

    @property
    def lump_share(self) -> float:
        """How much stiffer the same patch is with the lump than without it [1] (same mesh,
        same patch: the lump's own share, free of the mesh's)."""
        return self.k_o_over / self.k_o_over_without - 1.0

    @property
    def mesh_asymmetry(self) -> float:
        """Over over beside less 1 on the same mesh without the lump: the mesh's own share."""
        return self.k_o_over_without / self.k_o_beside_without - 1.0

    @property
    def felt(self) -> bool:
        """The rise exceeds one stiffness JND, and so does the lump's own share."""
        return min(self.rise, self.lump_share) > STIFFNESS_JND

    def as_dict(self, press_depth_m: float) -> dict[str, Any]:
        """The result as JSON; forces at ``press_depth_m`` [m] of indentation."""
        return {
            "lump_diameter_mm": round(self.diameter_m * 1e3, 3),
            "lump_top_depth_mm": round(self.depth_m * 1e3, 3),
            "lump_centre_depth_mm": round((self.depth_m + self.diameter_m / 2) * 1e3, 3),
            "stiffer_by": self.factor,
            "k_o_over_n_per_m": round(self.k_o_over, 2),
            "k_o_beside_n_per_m": round(self.k_o_beside, 2),
            "force_over_n": round(self.k_o_over * press_depth_m, 4),
            "force_beside_n": round(self.k_o_beside * press_depth_m, 4),
            "rise": round(self.rise, 4),
            "lump_share": round(self.lump_share, 4),
            "k_o_over_without_lump_n_per_m": round(self.k_o_over_without, 2),
            "k_o_beside_without_lump_n_per_m": round(self.k_o_beside_without, 2),
            "mesh_asymmetry": round(self.mesh_asymmetry, 4),
            "felt_by_jnd": self.felt,
            "lump_tetrahedra": self.lump_tets,
            "nodes": self.nodes,
        }


def lump_and_twin(
    diameter_m: float,
    depth_m: float,
    material: SolidMaterial,
    base: SolidMaterial,
    subdivisions: int = LUMP_SUBDIVISIONS,
) -> list[Inclusion]:
    """The lump (``material``) and its mirror twin of the solid's own material (``base``): the
    twin's surface refines the mesh beside the lump as the lump's refines it over the lump, so
    that over and beside are meshed alike (without it, today's P1 mesh is about 10 % softer
    over the lump's refined facets than beside them; docs/palpation.md)."""
    return [
        Inclusion(
            mesh=sphere_lump(diameter_m, depth_m, subdivisions=subdivisions),
            material=material,
            where="lump",
        ),
        Inclusion(
            mesh=sphere_lump(diameter_m, depth_m, side=-1.0, subdivisions=subdivisions),
            material=base,
            where="twin",
        ),
    ]


def measure(
    diameter_m: float,
    depth_m: float,
    factor: float = 10.0,
    base: SolidMaterial | None = None,
    subdivisions: int = 4,
    cache_dir: str | Path | None = None,
    lump_subdivisions: int = LUMP_SUBDIVISIONS,
) -> PalpationResult:
    """``K_o`` over a spherical lump ``factor`` times as stiff as ``base`` (default liver) and
    beside it over its twin, with and without the lump's material, on the default sphere
    (module docstring).

    Parameters
    ----------
    diameter_m, depth_m : float
        The lump's diameter and the depth of its top under the surface [m].
    factor : float
        The lump's Young's modulus over the solid's (> 0).
    base : SolidMaterial, optional
        The solid's material (default liver).
    subdivisions : int
        Icosphere subdivisions of the solid's surface shown (4: the server's default, 2562
        vertices); the solid is built as the server builds it
        (:func:`server.objects.fem.sphere_for_solid`: P2 on the parent icosphere).
    cache_dir : path, optional
        Where TetGen's volume meshes are cached.
    lump_subdivisions : int
        Icosphere subdivisions of the lump's and its twin's surfaces.

    Raises
    ------
    ValueError
        A lump that does not fit, or a factor not > 0.
    """
    if not (math.isfinite(factor) and factor > 0.0):
        raise ValueError(f"factor must be > 0, got {factor!r}")
    base = base or SOLID_PRESETS["liver"]
    stiff = replace(base, name=f"{base.name}*{factor:g}", young_pa=base.young_pa * factor)
    mesh, element = sphere_for_solid(subdivisions)
    inclusions = lump_and_twin(diameter_m, depth_m, stiff, base, lump_subdivisions)
    nodes, tets = volume_with_inclusions(mesh, inclusions, cache_dir=cache_dir)
    params = replace(_static(solid_to_params(base, FemParams())), element=element)
    solid = FemSolid(mesh, params, volume=(nodes, tets))
    shown = solid.rest_vertices
    radius = float(np.linalg.norm(shown, axis=1).max())
    keys = [
        int(np.argmin(np.linalg.norm(shown - radius * lump_direction(side=s), axis=1)))
        for s in (1.0, -1.0)
    ]
    without = solid.contact_stiffness(keys)
    mats: ElementMaterials = element_materials(solid.nodes, solid.tets, base, inclusions)
    lumped = FemSolid(mesh, params, volume=(nodes, tets), materials=mats)
    with_lump = lumped.contact_stiffness(keys)
    return PalpationResult(
        diameter_m=float(diameter_m),
        depth_m=float(depth_m),
        factor=float(factor),
        k_o_over=float(with_lump[0]),
        k_o_beside=float(with_lump[1]),
        k_o_over_without=float(without[0]),
        k_o_beside_without=float(without[1]),
        lump_tets=int((mats.labels == 1).sum()),
        nodes=len(solid.nodes),
    )


def _static(params: FemParams) -> FemParams:
    """``params`` as the static model without warping (no modes: ``K_o`` is static anyway)."""
    return replace(params, density_kg_m3=0.0, warp=False)


def smallest_felt(results: Sequence[PalpationResult]) -> float | None:
    """The smallest lump diameter [m] felt among ``results`` (None: none felt)."""
    felt = [r.diameter_m for r in results if r.felt]
    return min(felt) if felt else None


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
        )
        return out.stdout.strip()
    except OSError:
        return "unknown"


def run(
    diameters_mm: Sequence[float],
    depths_mm: Sequence[float],
    factor: float,
    press_depth_m: float,
    cache_dir: str | Path | None = None,
    big_depths_mm: Sequence[float] = (10.0, 20.0, 30.0),
) -> dict[str, Any]:
    """The palpation measurement: a 10 mm lump at each of ``depths_mm``, lumps of each of
    ``diameters_mm`` 10 mm deep, and a 30 mm lump at each of ``big_depths_mm``, ``factor`` times
    as stiff as liver; JSON-ready (depths of the lump's top, diameters [mm])."""
    clock = time.perf_counter()
    by_depth = [measure(0.010, d * 1e-3, factor, cache_dir=cache_dir) for d in depths_mm]
    by_size = [measure(D * 1e-3, 0.010, factor, cache_dir=cache_dir) for D in diameters_mm]
    big = [measure(0.030, d * 1e-3, factor, cache_dir=cache_dir) for d in big_depths_mm]
    smallest = smallest_felt(by_size)
    deepest = [r.depth_m for r in by_depth if r.felt]
    return {
        "what": "K_o of the FEM liver sphere (radius 0.1 m, 2562 surface vertices, the 15 mm "
        "finger pad) over a spherical lump and at the mirror point beside it over a twin of "
        "liver, at equal depth; K_o with the lump from per-element materials assembled by "
        "group (server.objects.inclusions.stiffness_by_groups)",
        "patch_radius_mm": FemParams().patch_radius_m * 1e3,
        "date": _dt.date.today().isoformat(),
        "commit": _commit(),
        "command": "python -m haptic_collab.research.palpation " + " ".join(sys.argv[1:]),
        "machine": platform.platform(),
        "tetgen_switches": TETGEN_SWITCHES,
        "stiffness_jnd": STIFFNESS_JND,
        "press_depth_mm": press_depth_m * 1e3,
        "lump_angle_deg": math.degrees(LUMP_ANGLE_RAD),
        "stiffer_by": factor,
        "lump_10mm_by_depth": [r.as_dict(press_depth_m) for r in by_depth],
        "lumps_10mm_deep_by_diameter": [r.as_dict(press_depth_m) for r in by_size],
        "lump_30mm_by_depth": [r.as_dict(press_depth_m) for r in big],
        "smallest_felt_diameter_mm": None if smallest is None else smallest * 1e3,
        "deepest_felt_10mm_lump_mm": max(deepest) * 1e3 if deepest else None,
        "seconds": round(time.perf_counter() - clock, 1),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m haptic_collab.research.palpation``: print and optionally write the JSON."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=None, help="write the JSON here")
    p.add_argument("--diameters-mm", type=float, nargs="+", default=[6, 10, 14, 20, 24, 30, 40])
    p.add_argument("--depths-mm", type=float, nargs="+", default=[3, 5, 10, 15, 20])
    p.add_argument("--stiffer-by", type=float, default=10.0)
    p.add_argument("--press-depth-mm", type=float, default=5.0)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="haptic-palpation-") as cache:
        result = run(
            args.diameters_mm, args.depths_mm, args.stiffer_by, args.press_depth_mm * 1e-3, cache
        )
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
