"""Materials of the deformable object: SI parameters, cited presets and TOML files.

A :class:`Material` holds what a user of ``--material`` chooses: the membrane tension, the
bending stiffness, the foundation, the bulk modulus of the enclosed liquid and the damping, in SI
units, plus where the numbers come from. :func:`material_to_params` turns it into the
:class:`~server.objects.balloon.BalloonParams` of the water-balloon model (DESIGN section 5)::

    K = tau * L + D * L A^-1 L + k_f * A + kappa * a a^T,    kappa = K_w / V

The only conversion is the water term: the balloon's ``bulk`` ``kappa`` [N/m^5] is the pressure
rise [Pa] per m^3 of enclosed volume lost, so for a liquid of bulk modulus ``K_w`` [Pa]
(``dp = -K_w dV / V``) it is ``K_w / V`` with ``V`` [m^3] the rest volume the mesh encloses
(``trimesh.Trimesh.volume``): 2.2 GPa / 4.18e-3 m^3 = 5.26e11 N/m^5 on the default 0.1 m
icosphere. Every other field maps one to one.

Presets (docs/materials.md lists the derivations and the measured K_o):

``water-balloon``
    A latex party balloon filled with water to a radius of 0.1 m. Natural rubber: shear modulus
    G = 0.4 MPa (E = 3G = 1.2 MPa, nu = 0.5; Treloar 1975). Wall 0.2 mm thick deflated, stress-
    free radius 3 cm, so stretched lambda = 3.33 times and 0.2 mm / lambda^2 = 18 um thin when
    filled. Overpressure of a neo-Hookean balloon (Treloar 1975; Mueller & Strehlow 2004)
    ``p = 2 G h0 / R0 (1/lambda - 1/lambda^7)`` = 1.6 kPa ("a few kPa", as measured for rubber
    balloons by Merritt & Weinhaus 1978), tension by Laplace's law ``tau = p R / 2`` = 80 N/m;
    bending ``D = E h^3 / (12 (1 - nu^2))`` = 7.8e-10 N*m (Timoshenko & Woinowsky-Krieger 1959);
    no foundation (nothing but tension and water holds the film); water K_w = 2.2 GPa (Kell
    1975).
``silicone-ball``
    A 7 mm Sylgard 184 silicone shell (E = 1.32 MPa cured at 25 C, Johnston et al. 2014,
    nu = 0.5): D = 0.050 N*m; filled with water at 1 kPa overpressure: tau = 50 N/m; a weak
    foundation of 100 N/m^3. This is what :class:`BalloonParams`' defaults are physically (their
    ``bulk`` 1e12 N/m^5 is 4.2 GPa on the default mesh instead of water's 2.2 GPa, and their
    bending 0.05 N*m; K_o differs by 0.3 %).
``soft-tissue``
    Liver-like: K_o at the contact matches the indentation stiffness of an elastic half-space
    of healthy liver (E = 5.5 kPa, the mean of 429 healthy subjects by transient elastography,
    Roulot et al. 2008; nu = 0.5)
    under the same 15 mm raised-cosine finger-pad patch, 1.672 E a = 138 N/m
    (:func:`halfspace_patch_stiffness`; Boussinesq/Sneddon 1965). A fit, not a derivation:
    tension 20 N/m, no bending, foundation 1e5 N/m^3, water-like bulk 2.2 GPa. The stiff
    foundation makes the response local (top-to-side coupling about 1 %), as in a solid organ.

References
----------
- Treloar, L. R. G. (1975). *The Physics of Rubber Elasticity*, 3rd ed. Oxford: Clarendon.
- Mueller, I., & Strehlow, P. (2004). *Rubber and Rubber Balloons: Paradigms of
  Thermodynamics*. Lecture Notes in Physics 637. Berlin: Springer.
- Merritt, D. R., & Weinhaus, F. (1978). The pressure curve for a rubber balloon. *American
  Journal of Physics* 46(10), 976-977.
- Timoshenko, S., & Woinowsky-Krieger, S. (1959). *Theory of Plates and Shells*, 2nd ed.
  New York: McGraw-Hill.
- Kell, G. S. (1975). Density, thermal expansivity, and compressibility of liquid water from
  0 to 150 C. *Journal of Chemical & Engineering Data* 20(1), 97-105.
- Johnston, I. D., McCluskey, D. K., Tan, C. K. L., & Tracey, M. C. (2014). Mechanical
  characterization of bulk Sylgard 184 for microfluidics and microengineering. *Journal of
  Micromechanics and Microengineering* 24(3), 035017.
- Roulot, D., Czernichow, S., Le Clesiau, H., Costes, J.-L., Vergnaud, A.-C., & Beaugrand, M.
  (2008). Liver stiffness values in apparently healthy subjects: influence of gender and
  metabolic syndrome. *Journal of Hepatology* 48(4), 606-613.
- Sneddon, I. N. (1965). The relation between load and penetration in the axisymmetric
  Boussinesq problem for a punch of arbitrary profile. *International Journal of Engineering
  Science* 3(1), 47-57.

Nothing here uses threads, sockets or clocks.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from pydantic import AfterValidator, Field, ValidationError

from haptic_collab.server.objects.balloon import BalloonParams
from haptic_collab.server.toml_file import read_toml
from haptic_collab.shared.checks import NonNegFinite, PositiveFinite, describe, params_dataclass
from haptic_collab.shared.checks import positive as _positive
from haptic_collab.shared.types import FloatArray

if TYPE_CHECKING:
    from haptic_collab.server.objects.balloon import Balloon


class MaterialError(ValueError):
    """A material that cannot be used: unknown preset or file, bad TOML, bad key or value.

    The message names the file (when there is one) and the offending key.
    """


#: Numeric fields of :class:`Material` with their units (TOML keys are these names).
_UNITS: dict[str, str] = {
    "tension_n_per_m": "N/m",
    "bending_n_m": "N*m",
    "foundation_n_per_m3": "N/m^3",
    "bulk_modulus_pa": "Pa",
    "damping_pa_s_per_m": "Pa*s/m",
}
#: TOML keys that must be present.
REQUIRED_KEYS = ("tension_n_per_m", "bending_n_m", "foundation_n_per_m3", "bulk_modulus_pa")
#: TOML keys that may be left out (``damping_pa_s_per_m`` 0, ``name`` the file's stem,
#: ``source`` "file <path>").
OPTIONAL_KEYS = ("damping_pa_s_per_m", "name", "source")


def _non_blank(name: str) -> str:
    if not name.strip():
        raise ValueError(f"must be a non-empty string, got {name!r}")
    return name


@params_dataclass(frozen=True, slots=True)
class Material:
    """The physical parameters of a deformable object, SI units (DESIGN section 5).

    Parameters
    ----------
    name : str
        Short name (a preset's name, or a file's stem).
    tension_n_per_m : float
        Membrane tension tau [N/m], > 0 (for a pressurised sphere, Laplace ``tau = p R / 2``).
    bending_n_m : float
        Bending stiffness D [N*m], >= 0 (for a plate, ``D = E h^3 / (12 (1 - nu^2))``).
    foundation_n_per_m3 : float
        Foundation (skin) stiffness k_f [N/m^3], >= 0: restoring pressure [Pa] per metre of
        normal displacement. Large values make the response local and kill the coupling.
    bulk_modulus_pa : float
        Bulk modulus K_w [Pa] of the enclosed liquid, >= 0 (water 2.2e9). The model's
        ``kappa = K_w / V`` [N/m^5], V the enclosed rest volume (:func:`bulk_term`).
    damping_pa_s_per_m : float
        Visco-elastic damping b [Pa*s/m = N*s/m^3], >= 0: damping pressure per normal speed
        (paper eq. 9). 0 is the static admittance of eq. (6).
    source : str
        Where the numbers come from (citations, or "file <path>").

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) A number that is not a finite number (a bool is not
        one) or out of its range, a name or source that is not a string, or a blank name.
        :func:`material_from_mapping` says the same as a :class:`MaterialError` on one line,
        with the file and the unit.
    """

    name: Annotated[str, Field(min_length=1), AfterValidator(_non_blank)]
    tension_n_per_m: PositiveFinite
    bending_n_m: NonNegFinite
    foundation_n_per_m3: NonNegFinite
    bulk_modulus_pa: NonNegFinite
    damping_pa_s_per_m: NonNegFinite = 0.0
    source: str = ""

    def summary(self) -> str:
        """One line for a log: name, the five parameters with units, and the source."""
        return (
            f"{self.name}: tension {self.tension_n_per_m:.3g} N/m, bending "
            f"{self.bending_n_m:.3g} N*m, foundation {self.foundation_n_per_m3:.3g} N/m^3, "
            f"bulk modulus {self.bulk_modulus_pa:.3g} Pa, damping "
            f"{self.damping_pa_s_per_m:.3g} Pa*s/m ({self.source or 'no source given'})"
        )


# ------------------------------------------------------------------------------ physics helpers


def _poisson(nu: float) -> float:
    v = float(nu)
    if not (math.isfinite(v) and -1.0 < v <= 0.5):
        raise ValueError(f"poisson must be in (-1, 0.5], got {nu!r}")
    return v


def plate_bending_stiffness(young_pa: float, thickness_m: float, poisson: float = 0.5) -> float:
    """Flexural rigidity of a thin plate, ``D = E h^3 / (12 (1 - nu^2))`` [N*m].

    Timoshenko & Woinowsky-Krieger (1959), eq. (3).

    Parameters
    ----------
    young_pa : float
        Young's modulus E [Pa], > 0.
    thickness_m : float
        Wall thickness h [m], > 0 (of the wall *as it is* in the object, e.g. stretched).
    poisson : float
        Poisson's ratio nu in (-1, 0.5]; 0.5 for rubber and silicone (incompressible).

    Raises
    ------
    ValueError
        A value out of range.
    """
    e = _positive("young_pa", young_pa)
    h = _positive("thickness_m", thickness_m)
    nu = _poisson(poisson)
    return e * h**3 / (12.0 * (1.0 - nu * nu))


def laplace_tension(overpressure_pa: float, radius_m: float) -> float:
    """Membrane tension of a pressurised sphere by Laplace's law, ``tau = p R / 2`` [N/m].

    Parameters
    ----------
    overpressure_pa : float
        Inside minus outside pressure p [Pa], > 0.
    radius_m : float
        Sphere radius R [m], > 0.

    Raises
    ------
    ValueError
        A value not finite and > 0.
    """
    return _positive("overpressure_pa", overpressure_pa) * _positive("radius_m", radius_m) / 2.0


def neo_hookean_balloon_pressure(
    shear_modulus_pa: float,
    thickness_unstretched_m: float,
    radius_unstretched_m: float,
    radius_m: float,
) -> float:
    """Overpressure [Pa] of a neo-Hookean spherical balloon inflated to ``radius_m``.

    ``p = 2 G h0 / R0 * (1 / lambda - 1 / lambda^7)``, ``lambda = R / R0`` (Treloar 1975;
    Mueller & Strehlow 2004, ch. 3). It peaks at ``lambda = 7^(1/6) = 1.38`` and then falls, the
    shape Merritt & Weinhaus (1978) measured on rubber balloons. The membrane tension that goes
    with it, ``p R / 2 = G h0 (1 - lambda^-6)``, is nearly ``G h0`` once ``lambda > 2``.

    Parameters
    ----------
    shear_modulus_pa : float
        Small-strain shear modulus G [Pa] (E / 3 for an incompressible rubber), > 0.
    thickness_unstretched_m, radius_unstretched_m : float
        Wall thickness h0 and radius R0 [m] of the stress-free balloon, > 0.
    radius_m : float
        Inflated radius R [m], >= R0.

    Raises
    ------
    ValueError
        A value out of range.
    """
    g = _positive("shear_modulus_pa", shear_modulus_pa)
    h0 = _positive("thickness_unstretched_m", thickness_unstretched_m)
    r0 = _positive("radius_unstretched_m", radius_unstretched_m)
    r = _positive("radius_m", radius_m)
    if r < r0:
        raise ValueError(f"radius_m ({r:g}) must be >= radius_unstretched_m ({r0:g})")
    lam = r / r0
    return 2.0 * g * h0 / r0 * (1.0 / lam - lam**-7)


def halfspace_patch_stiffness(
    young_pa: float, patch_radius_m: float, poisson: float = 0.5, *, n_radial: int = 600
) -> float:
    """Indentation stiffness [N/m] of an elastic half-space under the finger-pad patch load.

    The same raised-cosine pressure the balloon uses (weight ``(1 + cos(pi r / a)) / 2`` per
    unit area for ``r < a``, :meth:`server.objects.balloon.Balloon.patch`), and the same
    definition of stiffness: ``1 / (beta^T C beta)``, the force over the load-weighted mean
    displacement. With Boussinesq's point-load solution ``w = (1 - nu^2) / (pi E r)`` and the
    Hankel transform ``Q(k)`` of the normalised load,
    ``beta^T C beta = (1 - nu^2) / (pi E) * int_0^inf Q(k)^2 dk`` = ``0.797 (1 - nu^2) / (E a)``,
    so ``K = 1.254 E a / (1 - nu^2)`` (1.672 E a for nu = 0.5). For a uniform pressure this
    gives the classical ``3 pi^2 E a / (16 (1 - nu^2))`` (Sneddon 1965's framework), which the
    tests check.

    Parameters
    ----------
    young_pa : float
        Young's modulus E [Pa] of the tissue, > 0.
    patch_radius_m : float
        Patch radius a [m], > 0 (``BalloonParams.patch_radius_m``, 0.015 by default).
    poisson : float
        Poisson's ratio in (-1, 0.5]; 0.5 for soft tissue (nearly incompressible).
    n_radial : int
        Radial quadrature points (>= 50).

    Raises
    ------
    ValueError
        A value out of range.
    """
    e = _positive("young_pa", young_pa)
    a = _positive("patch_radius_m", patch_radius_m)
    nu = _poisson(poisson)
    if n_radial < 50:
        raise ValueError(f"n_radial must be >= 50, got {n_radial}")
    coefficient = disc_load_compliance(lambda r: 0.5 * (1.0 + np.cos(np.pi * r)), n_radial)
    return e * a / ((1.0 - nu * nu) * coefficient)


def disc_load_compliance(shape: Callable[[FloatArray], FloatArray], n_radial: int = 600) -> float:
    """Half-space compliance coefficient of an axisymmetric load on the unit disc.

    ``c = (1/pi) int_0^inf Q(k)^2 dk`` with ``Q(k) = 2 pi int_0^1 q(r) J0(k r) r dr`` the
    Hankel transform of the load ``q`` normalised to total 1, so that the load-weighted mean
    displacement per unit force on a half-space is ``c (1 - nu^2) / (E a)`` for a disc of
    radius a. Midpoint rules in r and in k up to k = 400 (the uniform disc's 16 / (3 pi^2) is
    reproduced to 1e-6).

    Parameters
    ----------
    shape : callable
        ``shape(r)`` for ``r`` (n,) float in (0, 1): load per unit area, any scale.
    n_radial : int
        Radial quadrature points.
    """
    from scipy.special import j0

    r = (np.arange(n_radial) + 0.5) / n_radial
    dr = 1.0 / n_radial
    q = np.asarray(shape(r), dtype=np.float64)
    q = q / (2.0 * np.pi * float(np.sum(q * r)) * dr)
    k_max, n_k = 400.0, 6000
    dk = k_max / n_k
    k = (np.arange(n_k) + 0.5) * dk
    transform = 2.0 * np.pi * (j0(np.outer(k, r)) @ (q * r)) * dr
    return float(np.sum(transform**2) * dk / np.pi)


def bulk_term(bulk_modulus_pa: float, volume_m3: float) -> float:
    """The balloon's water term ``kappa = K_w / V`` [N/m^5].

    ``dp = -K_w dV / V`` for a liquid of bulk modulus ``K_w`` [Pa] filling the rest volume
    ``V`` [m^3]; the model's pressure change is ``-kappa a^T w`` with ``a^T w`` the volume
    change, hence ``kappa = K_w / V``.

    Raises
    ------
    ValueError
        ``bulk_modulus_pa`` negative or not finite, ``volume_m3`` not finite and > 0.
    """
    k = float(bulk_modulus_pa)
    if not (math.isfinite(k) and k >= 0.0):
        raise ValueError(f"bulk_modulus_pa must be a finite number >= 0, got {bulk_modulus_pa!r}")
    return k / _positive("volume_m3", volume_m3)


# ------------------------------------------------------------------------------------- presets
#: Water's bulk modulus [Pa] at 20 C (isothermal compressibility 4.59e-10 /Pa; Kell 1975).
WATER_BULK_MODULUS_PA = 2.2e9

# water-balloon: a latex party balloon filled with water to R = 0.1 m.
_LATEX_SHEAR_PA = 0.4e6  # natural rubber, Treloar 1975
_LATEX_H0_M = 0.2e-3  # deflated wall
_LATEX_R0_M = 0.03  # stress-free radius
_BALLOON_R_M = 0.1  # filled radius (the default mesh)
_LATEX_STRETCH = _BALLOON_R_M / _LATEX_R0_M
_LATEX_PRESSURE_PA = neo_hookean_balloon_pressure(
    _LATEX_SHEAR_PA, _LATEX_H0_M, _LATEX_R0_M, _BALLOON_R_M
)
_LATEX_FILM_M = _LATEX_H0_M / _LATEX_STRETCH**2  # rubber is incompressible: h = h0 / lambda^2

# silicone-ball: a 7 mm Sylgard 184 shell (E = 1.32 MPa, Johnston et al. 2014) at 1 kPa.
_SYLGARD_YOUNG_PA = 1.32e6
_SILICONE_WALL_M = 7.0e-3
_SILICONE_PRESSURE_PA = 1.0e3

#: Healthy liver's Young's modulus [Pa] by transient elastography: the mean of 429 apparently
#: healthy subjects, 5.49 +- 1.59 kPa (Roulot et al. 2008), not an upper normal value.
LIVER_YOUNG_PA = 5.5e3

_PRESETS: dict[str, Material] = {
    "water-balloon": Material(
        name="water-balloon",
        tension_n_per_m=laplace_tension(_LATEX_PRESSURE_PA, _BALLOON_R_M),
        bending_n_m=plate_bending_stiffness(3.0 * _LATEX_SHEAR_PA, _LATEX_FILM_M, 0.5),
        foundation_n_per_m3=0.0,
        bulk_modulus_pa=WATER_BULK_MODULUS_PA,
        damping_pa_s_per_m=0.0,
        source=(
            "latex balloon filled with water to R = 0.1 m: natural rubber G = 0.4 MPa "
            "(Treloar 1975), 0.2 mm wall stretched 3.33x to 18 um; neo-Hookean overpressure "
            "1.6 kPa (Treloar 1975; Merritt & Weinhaus 1978), tau = p R / 2 (Laplace); "
            "D = E h^3 / (12 (1 - nu^2)) (Timoshenko & Woinowsky-Krieger 1959); "
            "water 2.2 GPa (Kell 1975)"
        ),
    ),
    "silicone-ball": Material(
        name="silicone-ball",
        tension_n_per_m=laplace_tension(_SILICONE_PRESSURE_PA, _BALLOON_R_M),
        bending_n_m=plate_bending_stiffness(_SYLGARD_YOUNG_PA, _SILICONE_WALL_M, 0.5),
        foundation_n_per_m3=100.0,
        bulk_modulus_pa=WATER_BULK_MODULUS_PA,
        damping_pa_s_per_m=0.0,
        source=(
            "7 mm Sylgard 184 shell, E = 1.32 MPa (Johnston et al. 2014), filled with water "
            "at 1 kPa: tau = p R / 2 = 50 N/m; weak 100 N/m^3 foundation; water 2.2 GPa "
            "(Kell 1975); the BalloonParams defaults"
        ),
    ),
    "soft-tissue": Material(
        name="soft-tissue",
        tension_n_per_m=20.0,
        bending_n_m=0.0,
        foundation_n_per_m3=1.0e5,
        bulk_modulus_pa=WATER_BULK_MODULUS_PA,
        damping_pa_s_per_m=0.0,
        source=(
            "liver-like: fitted so K_o matches a half-space of E = 5.5 kPa (healthy liver, "
            "transient elastography, Roulot et al. 2008) under the 15 mm finger-pad patch, "
            "1.672 E a = 138 N/m (Boussinesq; Sneddon 1965)"
        ),
    ),
}


#: The presets of ``--material NAME`` (read-only), in the order docs/materials.md lists them.
PRESETS: Mapping[str, Material] = MappingProxyType(_PRESETS)


# ------------------------------------------------------------------------------------- loading
def _suggest(key: str, known: tuple[str, ...]) -> str:
    close = difflib.get_close_matches(key, known, n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_table_keys(
    data: Mapping[str, object],
    where: str,
    required: tuple[str, ...],
    optional: tuple[str, ...],
    units: Mapping[str, str],
) -> None:
    """Refuse a material table with an unknown key (naming the closest known one) or a missing one.

    Raises
    ------
    MaterialError
        ``WHERE: unknown key ...`` or ``WHERE: missing required key ... [unit]``.
    """
    known = required + optional
    unknown = [k for k in data if k not in known]
    if unknown:
        k = unknown[0]
        raise MaterialError(
            f"{where}: unknown key {k!r}{_suggest(k, known)}; known keys: {', '.join(known)}"
        )
    missing = [k for k in required if k not in data]
    if missing:
        unit = units.get(missing[0])
        raise MaterialError(
            f"{where}: missing required key {missing[0]!r}"
            + (f" [{unit}]" if unit else "")
            + (f" (also missing: {', '.join(missing[1:])})" if len(missing) > 1 else "")
        )


def material_from_mapping(data: Mapping[str, object], where: str, default_name: str) -> Material:
    """A :class:`Material` from a TOML table (or any mapping), strictly checked.

    Parameters
    ----------
    data : mapping
        Keys :data:`REQUIRED_KEYS` (numbers) and optionally :data:`OPTIONAL_KEYS`.
    where : str
        Name used in error messages (the file path).
    default_name : str
        The material's name when ``data`` has no ``name``.

    Raises
    ------
    MaterialError
        An unknown key (with the closest known one), a missing required key, a value of the
        wrong type, NaN/inf or negative (zero tension), or a blank name. The message starts with
        ``where`` and names the key, e.g. ``WHERE: bending_n_m must be >= 0 [N*m], got -1e-06``.
    """
    check_table_keys(data, where, REQUIRED_KEYS, OPTIONAL_KEYS, _UNITS)
    for key in ("name", "source"):
        if key in data and not isinstance(data[key], str):
            raise MaterialError(f"{where}: {key} must be a string, got {data[key]!r}")
    values: dict[str, Any] = {key: data[key] for key in _UNITS if key in data}
    name = str(data.get("name", default_name))
    source = str(data.get("source", f"file {where}"))
    try:
        return Material(name=name, source=source, **values)
    except ValidationError as exc:
        raise MaterialError(f"{where}: {describe(exc, _UNITS)}") from None


def load_material_file(path: str | Path) -> Material:
    """Read a material from a TOML file (stdlib :mod:`tomllib`).

    The file holds top-level keys, e.g.::

        name = "my-balloon"                 # optional, default: the file's stem
        source = "measured on 2024-05-02"   # optional
        tension_n_per_m = 80.0
        bending_n_m = 7.8e-10
        foundation_n_per_m3 = 0.0
        bulk_modulus_pa = 2.2e9
        damping_pa_s_per_m = 0.0            # optional, default 0

    Raises
    ------
    MaterialError
        The file is missing or unreadable, is not valid TOML (the parser's line and column are
        given), or :func:`material_from_mapping` refuses its content.
    """
    p = Path(path)
    data = read_toml(p, "material", MaterialError)
    return material_from_mapping(data, str(p), default_name=p.stem)


def load_material(spec: str | Path) -> Material:
    """The material of ``--material NAME|FILE.toml``: a preset by name, else a TOML file.

    Parameters
    ----------
    spec : str or pathlib.Path
        A key of :data:`PRESETS` (``water-balloon``, ``silicone-ball``, ``soft-tissue``) or the
        path of a TOML file (:func:`load_material_file`).

    Raises
    ------
    MaterialError
        Neither a preset nor an existing file (the presets are listed, with the closest one), or
        a file that :func:`load_material_file` refuses.
    """
    if isinstance(spec, str) and spec in PRESETS:
        return PRESETS[spec]
    p = Path(spec)
    if p.suffix.lower() == ".toml" or p.exists():
        return load_material_file(p)
    names = tuple(PRESETS)
    raise MaterialError(
        f"unknown material {str(spec)!r}{_suggest(str(spec), names)}: give a preset "
        f"({', '.join(names)}) or a .toml file"
    )


def material_to_params(
    material: Material, base: BalloonParams, *, volume_m3: float
) -> BalloonParams:
    """``base`` with the material's tension, bending, foundation, water and damping.

    Numerical fields of ``base`` (patch radius and spacing, base radius, simulation period,
    cache) are kept. ``bulk = material.bulk_modulus_pa / volume_m3`` (:func:`bulk_term`).

    Parameters
    ----------
    material : Material
    base : BalloonParams
    volume_m3 : float
        Rest volume V [m^3] the object's mesh encloses (``mesh.volume``), > 0.

    Returns
    -------
    BalloonParams

    Raises
    ------
    ValueError
        ``volume_m3`` not finite and > 0.
    """
    return replace(
        base,
        tension=material.tension_n_per_m,
        bending=material.bending_n_m,
        foundation=material.foundation_n_per_m3,
        bulk=bulk_term(material.bulk_modulus_pa, volume_m3),
        damping=material.damping_pa_s_per_m,
    )


def top_side_stiffness(balloon: Balloon) -> tuple[float, float]:
    """K_o [N/m] at the object's top and side, each contact alone (paper eq. 6-8).

    Top: the patch nearest the point ``(cx, cy, z_max)``; side: nearest ``(x_max, cy, cz)``,
    with ``c`` the bounding-box centre. On the default sphere these are the top pole and an
    equator point, where the README's "about 310 N/m at the top and 270 N/m at the side" was
    measured (:meth:`Balloon.contact_stiffness`).

    Returns
    -------
    (float, float)
        ``(k_o_top, k_o_side)`` [N/m].
    """
    rest = balloon.rest_vertices
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    c = 0.5 * (lo + hi)
    top = balloon.patch_key(np.array([c[0], c[1], hi[2]]))
    side = balloon.patch_key(np.array([hi[0], c[1], c[2]]))
    k_top, k_side = (float(k) for k in balloon.contact_stiffness([top, side]))
    return k_top, k_side


def main() -> None:
    """Print every preset's parameters and K_o (top, side) on the default mesh."""
    from haptic_collab.server.objects.balloon import Balloon
    from haptic_collab.server.objects.mesh import default_balloon

    mesh = default_balloon()
    print(f"default mesh: {len(mesh.vertices)} vertices, volume {mesh.volume:.4e} m^3")
    print(
        f"half-space target of soft-tissue: "
        f"{halfspace_patch_stiffness(LIVER_YOUNG_PA, BalloonParams().patch_radius_m):.1f} N/m"
    )
    for material in PRESETS.values():
        params = material_to_params(material, BalloonParams(), volume_m3=float(mesh.volume))
        k_top, k_side = top_side_stiffness(Balloon(mesh, params))
        print(f"{material.summary()}\n    K_o top {k_top:.1f} N/m, side {k_side:.1f} N/m")


if __name__ == "__main__":
    main()
