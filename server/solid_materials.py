"""Materials of the FEM solid (``--object fem --material NAME|FILE.toml``): SI values with sources.

A :class:`SolidMaterial` is what the elastic solid of :mod:`server.objects.fem` needs: Young's
modulus, Poisson's ratio, density and Rayleigh damping, plus where the numbers come from.
:func:`solid_to_params` turns it into :class:`~server.objects.fem.FemParams`.

Every preset's numbers are in :data:`PRESET_SOURCES` with where each comes from and the strain
range it holds for; docs/materials.md's table of solid presets is generated from it
(:func:`preset_table`, ``python -m haptic_collab.server.solid_materials``) and a test keeps the
two equal.

Young's modulus (each preset's source below):

``liver``
    Healthy human liver, E = 5.5 kPa: the mean of 429 apparently healthy subjects by transient
    elastography (Roulot et al. 2008: 5.49 +- 1.59 kPa; men 5.81, women 5.23). Not the upper
    normal value: the range 2.3-5.9 kPa quoted before is the reference range of another cohort
    (530 healthy subjects, mean 4.1 kPa; Fung et al. 2013). Transient elastography reports
    E = 3 rho c^2 of a shear wave of micrometre amplitude: a small-strain, incompressible modulus.
``skin``
    Human skin on the forearm, E = 35 kPa: the dermis of a two-layer elastic model fitted to in
    vivo indentation (Pailler-Mattei, Bec and Zahouani 2008).
``ecoflex-0030``
    Smooth-On Ecoflex 00-30, E = 118 kPa: the data sheet gives only the 100 % modulus, 10 psi =
    68.9 kPa, the nominal stress at stretch 2, a secant. An incompressible neo-Hookean solid
    (Treloar 1975) in uniaxial tension has nominal stress ``P = (E / 3) (lam - lam^-2)``, so the
    small-strain modulus that gives 68.9 kPa at lam = 2 is ``E = 3 P / 1.75`` = 118 kPa
    (:func:`neo_hookean_young_from_secant`). The model is an assumption (one data-sheet point
    fixes its one parameter), not a measurement at small strain.
``sylgard-184``
    Dow Sylgard 184 PDMS, 10:1, cured at 25 C: E = 1.32 MPa in tension (Johnston et al. 2014;
    1.32-2.97 MPa for cures at 25-200 C). A stiff phantom: K_o under the finger pad is about
    50 kN/m, beyond a desktop device, which renders it at its own limit.

Poisson's ratio: every one of these materials is nearly incompressible (nu 0.49-0.5: tissue is
mostly water, transient elastography assumes nu = 0.5, and rubber's bulk modulus is about a
thousand times its shear modulus, Treloar 1975). nu = 0.45 is not a material value: it is the
linear tetrahedra's modelling choice, because they lock as nu approaches 0.5 (the solid grows far
too stiff). Its half-space punch stiffness ``2 a E / (1 - nu^2)`` is 6 % below an incompressible
one's; P1 locking at 0.45 makes the mesh about as much stiffer (docs/fem.md).

Damping: Kelvin-Voigt ``beta`` (``C = beta K``) gives a loss factor ``omega beta`` that grows
with frequency: beta = 0.01 s gives 0.06 at 1 Hz and 0.63 at 10 Hz. Liver's measured loss factor
is nearly constant instead: its shear modulus follows a power law in frequency, with
``G''/G' = tan(0.15 pi / 2) = 0.24`` over 40-100 Hz in bovine liver ex vivo (Sinkus et al. 2006)
and a power law below 50 Hz in bovine liver by rheometry and in healthy human liver in vivo by
MR elastography (Klatt et al. 2009; Asbach et al. 2008: viscosity 7.3 Pa s beside shear moduli
1.2-2.0 kPa, a time constant eta / mu of 4-6 ms). No Rayleigh pair gives a constant loss factor;
beta = 0.01 s gives liver's 0.24 at 3.8 Hz, within the band of a hand's voluntary motion, twice
too much at 8 Hz, and alone it damped too little below: 0.06 at 1 Hz, 0.11 at the liver ball's
lowest modes (1.7 Hz). The presets therefore add mass-proportional damping ``alpha M`` (loss factor
``alpha / omega``), alpha = 1.11 1/s, so that the loss factor is liver's 0.24 at 1 Hz as well:
0.21 at 1.7-2 Hz and 0.29 at 3.8 Hz (:data:`PRESET_ALPHA_PER_S`). Without it a resting user's
hand kept the ball's 1.7 Hz rocking going after another user's palpating sweep (a 1-1.7 mm
shake in 3 of 6 demo runs; 0.15-0.22 mm with it in 3 of 3; docs/palpation.md). The same alpha
and beta on the other presets are unsourced (kept so that every preset damps its contact modes
alike).

Density: liver 1060 and skin 1100 kg/m^3 are unsourced here (soft tissue is 1000-1100 kg/m^3);
Ecoflex 00-30 1070 kg/m^3 is the data sheet's specific gravity 1.07; Sylgard 184 1030 kg/m^3 is
unsourced here (Dow's data sheet lists 1.03 for the cured elastomer; not checked for this
version).

References
----------
- Roulot, D., Czernichow, S., Le Clesiau, H., Costes, J.-L., Vergnaud, A.-C., & Beaugrand, M.
  (2008). Liver stiffness values in apparently healthy subjects: influence of gender and
  metabolic syndrome. *Journal of Hepatology* 48(4), 606-613.
- Fung, J., Lee, C.-k., Chan, M., Seto, W.-k., Wong, D. K.-h., Lai, C.-l., & Yuen, M.-f. (2013).
  Defining normal liver stiffness range in a normal healthy Chinese population without liver
  disease. *PLoS ONE* 8(12), e85067.
- Pailler-Mattei, C., Bec, S., & Zahouani, H. (2008). In vivo measurements of the elastic
  mechanical properties of human skin by indentation tests. *Medical Engineering & Physics*
  30(5), 599-606.
- Smooth-On, Ecoflex Series technical bulletin (Ecoflex 00-30: 100 % modulus 10 psi, specific
  gravity 1.07 g/cc, elongation at break 900 %).
- Treloar, L. R. G. (1975). *The Physics of Rubber Elasticity*, 3rd ed. Oxford: Clarendon.
- Johnston, I. D., McCluskey, D. K., Tan, C. K. L., & Tracey, M. C. (2014). Mechanical
  characterization of bulk Sylgard 184 for microfluidics and microengineering. *J. Micromech.
  Microeng.* 24(3), 035017.
- Sinkus, R., Bercoff, J., Robert, B., Fink, M., & Tanter, M. (2006). Proc. ISMRM 14, abstract
  2560 (complex shear modulus of bovine liver ex vivo, 40-100 Hz).
- Klatt, D., Friedrich, C., Asbach, P., Nuzha, H., Rettig, K., Papazoglou, S., Hamhaber, U.,
  Braun, J., & Sack, I. (2009). Proc. ISMRM 17, abstract 2503 (bovine liver by oscillatory
  rheometry: a power law below 50 Hz).
- Asbach, P., Klatt, D., Hamhaber, U., Braun, J., Somasundaram, R., Hamm, B., & Sack, I. (2008).
  Assessment of liver viscoelasticity using multifrequency MR elastography. *Magnetic Resonance
  in Medicine* 60(2), 373-379.

Nothing here uses threads, sockets or clocks.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from pydantic import ValidationError

from haptic_collab.server.materials import (
    LIVER_YOUNG_PA,
    MaterialError,
    _suggest,
    check_table_keys,
)
from haptic_collab.server.objects.fem import FemParams, Poisson
from haptic_collab.server.toml_file import read_toml
from haptic_collab.shared.checks import NonNegFinite, PositiveFinite, describe, params_dataclass

#: Numeric keys of a solid material file, with their units.
_UNITS: dict[str, str] = {
    "young_pa": "Pa",
    "poisson": "1",
    "density_kg_m3": "kg/m^3",
    "rayleigh_alpha_per_s": "1/s",
    "rayleigh_beta_s": "s",
}
#: Keys a solid material file must have.
REQUIRED_KEYS = ("young_pa", "poisson", "density_kg_m3", "source")
#: Keys it may have (damping 0 and 0, ``name`` the file's stem).
OPTIONAL_KEYS = ("rayleigh_alpha_per_s", "rayleigh_beta_s", "name")


@params_dataclass(frozen=True, slots=True)
class SolidMaterial:
    """An isotropic linear elastic material, SI units.

    Parameters
    ----------
    name : str
    young_pa : float
        Young's modulus E [Pa], > 0.
    poisson : float
        Poisson's ratio nu in (-1, 0.5).
    density_kg_m3 : float
        Density [kg/m^3], >= 0.
    rayleigh_alpha_per_s, rayleigh_beta_s : float
        Rayleigh damping ``C = alpha M + beta K`` [1/s], [s], >= 0.
    source : str
        Where the numbers come from.

    Raises
    ------
    pydantic.ValidationError
        A field out of range.
    """

    name: str
    young_pa: PositiveFinite
    poisson: Poisson
    density_kg_m3: NonNegFinite
    rayleigh_alpha_per_s: NonNegFinite = 0.0
    rayleigh_beta_s: NonNegFinite = 0.01
    source: str = ""

    def summary(self) -> str:
        """One line for the server's log."""
        return (
            f"{self.name}: E {self.young_pa:g} Pa, nu {self.poisson:g}, "
            f"{self.density_kg_m3:g} kg/m^3 ({self.source})"
        )


#: One psi in pascals (exact: 0.45359237 kg * 9.80665 m/s^2 / 0.0254^2 m^2).
PSI_PA = 0.45359237 * 9.80665 / 0.0254**2
#: Ecoflex 00-30's 100 % modulus [Pa]: the nominal stress at stretch 2, 10 psi (data sheet).
ECOFLEX_0030_100_MODULUS_PA = 10.0 * PSI_PA
#: Kelvin-Voigt beta [s] of every preset (module docstring: liver's loss factor at 3.8 Hz).
PRESET_BETA_S = 0.01
#: Mass-proportional Rayleigh alpha [1/s] of every preset: liver's loss factor 0.24 at 1 Hz with
#: :data:`PRESET_BETA_S` (module docstring): ``(0.24 - 2 pi beta) 2 pi``.
PRESET_ALPHA_PER_S = 1.11
#: Poisson's ratio of every preset: the P1 element's choice, not a material value.
PRESET_POISSON = 0.45


def neo_hookean_young_from_secant(nominal_stress_pa: float, stretch: float) -> float:
    """Small-strain Young's modulus [Pa] of an incompressible neo-Hookean solid that carries
    ``nominal_stress_pa`` in uniaxial tension at ``stretch``.

    Uniaxial nominal (first Piola-Kirchhoff) stress ``P = mu (lam - lam^-2)`` with shear modulus
    ``mu = E / 3`` (Treloar 1975), so ``E = 3 P / (lam - lam^-2)``. A rubber data sheet's
    "100 % modulus" is ``P`` at ``lam = 2``: ``E = P / 0.583``.

    Parameters
    ----------
    nominal_stress_pa : float
        Force over the undeformed cross-section [Pa], > 0.
    stretch : float
        Stretch lam = L / L0 [1], > 1.

    Returns
    -------
    float
        E [Pa].

    Raises
    ------
    ValueError
        A stress not finite and > 0, or a stretch not finite and > 1.
    """
    p, lam = float(nominal_stress_pa), float(stretch)
    if not (math.isfinite(p) and p > 0.0):
        raise ValueError(f"nominal_stress_pa must be finite and > 0, got {nominal_stress_pa!r}")
    if not (math.isfinite(lam) and lam > 1.0):
        raise ValueError(f"stretch must be finite and > 1, got {stretch!r}")
    return 3.0 * p / (lam - lam**-2)


SOLID_PRESETS: Mapping[str, SolidMaterial] = MappingProxyType(
    {
        "liver": SolidMaterial(
            name="liver",
            young_pa=LIVER_YOUNG_PA,
            poisson=PRESET_POISSON,
            density_kg_m3=1060.0,
            rayleigh_alpha_per_s=PRESET_ALPHA_PER_S,
            rayleigh_beta_s=PRESET_BETA_S,
            source="transient elastography, mean of 429 healthy subjects, Roulot et al. 2008 "
            "(J Hepatol 48:606)",
        ),
        "skin": SolidMaterial(
            name="skin",
            young_pa=35.0e3,
            poisson=PRESET_POISSON,
            density_kg_m3=1100.0,
            rayleigh_alpha_per_s=PRESET_ALPHA_PER_S,
            rayleigh_beta_s=PRESET_BETA_S,
            source="dermis, in vivo indentation, Pailler-Mattei et al. 2008 (Med Eng Phys 30:599)",
        ),
        "ecoflex-0030": SolidMaterial(
            name="ecoflex-0030",
            young_pa=round(neo_hookean_young_from_secant(ECOFLEX_0030_100_MODULUS_PA, 2.0), -2),
            poisson=PRESET_POISSON,
            density_kg_m3=1070.0,
            rayleigh_alpha_per_s=PRESET_ALPHA_PER_S,
            rayleigh_beta_s=PRESET_BETA_S,
            source="Smooth-On Ecoflex 00-30 data sheet, 100 % modulus 10 psi, small-strain E of "
            "an incompressible neo-Hookean solid (Treloar 1975)",
        ),
        "sylgard-184": SolidMaterial(
            name="sylgard-184",
            young_pa=1.32e6,
            poisson=PRESET_POISSON,
            density_kg_m3=1030.0,
            rayleigh_alpha_per_s=PRESET_ALPHA_PER_S,
            rayleigh_beta_s=PRESET_BETA_S,
            source="10:1, cured at 25 C, Johnston et al. 2014 (J Micromech Microeng 24:035017)",
        ),
    }
)


@dataclass(frozen=True, slots=True)
class PresetSource:
    """Where each number of a solid preset comes from, as docs/materials.md lists it.

    Parameters
    ----------
    young, poisson, density, damping : str
        The source of E, nu, the density and beta, or ``"unsourced"`` with why the value is
        kept.
    strain_range : str
        The strains the linear material holds for, from its source.
    """

    young: str
    poisson: str
    density: str
    damping: str
    strain_range: str


_NU = "0.45: P1 choice; material about 0.5 (incompressible)"
_BETA_LIVER = (
    "loss factor 0.24 at 1 Hz and 3.8 Hz (0.21 at 2 Hz); liver's is about 0.24, flat in "
    "frequency (Sinkus 2006; Asbach 2008; Klatt 2009)"
)
_BETA_UNSOURCED = "unsourced (liver's values)"

#: The sources of every preset's numbers (module docstring; :func:`preset_table`).
PRESET_SOURCES: Mapping[str, PresetSource] = MappingProxyType(
    {
        "liver": PresetSource(
            young="transient elastography, mean of 429 healthy subjects (Roulot et al. 2008)",
            poisson=_NU,
            density="unsourced (soft tissue 1000-1100)",
            damping=_BETA_LIVER,
            strain_range="small: a shear wave of micrometre amplitude",
        ),
        "skin": PresetSource(
            young="dermis of a two-layer fit to in vivo indentation (Pailler-Mattei et al. 2008)",
            poisson=_NU,
            density="unsourced",
            damping=_BETA_UNSOURCED,
            strain_range="small: the indentation's elastic fit (depths not checked here)",
        ),
        "ecoflex-0030": PresetSource(
            young="100 % modulus 10 psi (Smooth-On data sheet) through a neo-Hookean solid "
            "(Treloar 1975): E = 3 P / 1.75",
            poisson=_NU,
            density="specific gravity 1.07 (data sheet)",
            damping=_BETA_UNSOURCED,
            strain_range="the neo-Hookean fit: small strain to stretch 2 (one point fixes it)",
        ),
        "sylgard-184": PresetSource(
            young="tensile, 10:1, cured at 25 C (Johnston et al. 2014; 1.32-2.97 MPa by cure)",
            poisson=_NU,
            density="unsourced (data sheet value 1.03 not checked)",
            damping=_BETA_UNSOURCED,
            strain_range="the tensile test's linear part",
        ),
    }
)


def _si(value: float, unit: str) -> str:
    """``5.5 kPa``, ``118 kPa``, ``1.32 MPa``: ``value`` [unit] with an SI prefix."""
    for factor, prefix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= factor:
            return f"{value / factor:.3g} {prefix}{unit}"
    return f"{value:.3g} {unit}"


def preset_table() -> str:
    """The solid presets as the Markdown table of docs/materials.md (one row a preset).

    Columns: preset, E, nu, density, alpha, beta, then the source of E, of nu, of the density, of
    the damping, and the strain range, from :data:`SOLID_PRESETS` and :data:`PRESET_SOURCES`.
    """
    head = (
        "| preset | E | nu | density [kg/m^3] | alpha [1/s] | beta [s] | E from | nu "
        "| density from | damping from | strain range |"
    )
    rows = [head, "|" + "---|" * 11]
    for name, m in SOLID_PRESETS.items():
        src = PRESET_SOURCES[name]
        rows.append(
            f"| `{name}` | {_si(m.young_pa, 'Pa')} | {m.poisson:g} | {m.density_kg_m3:g} "
            f"| {m.rayleigh_alpha_per_s:g} | {m.rayleigh_beta_s:g} | {src.young} | {src.poisson} "
            f"| {src.density} "
            f"| {src.damping} | {src.strain_range} |"
        )
    return "\n".join(rows)


def solid_from_mapping(data: Mapping[str, object], where: str, default_name: str) -> SolidMaterial:
    """A :class:`SolidMaterial` from a TOML table, strictly checked.

    Raises
    ------
    MaterialError
        An unknown key (with the closest known one), a missing key (``source`` included: a
        material says where its numbers come from), a wrong type or a value out of range; the
        message starts with ``where`` and names the key.
    """
    check_table_keys(data, where, REQUIRED_KEYS, OPTIONAL_KEYS, _UNITS)
    for key in ("name", "source"):
        if key in data and not (isinstance(data[key], str) and str(data[key]).strip()):
            raise MaterialError(f"{where}: {key} must be a non-empty string, got {data[key]!r}")
    values: dict[str, Any] = {key: data[key] for key in _UNITS if key in data}
    if isinstance(values.get("poisson"), int) and not isinstance(values["poisson"], bool):
        values["poisson"] = float(values["poisson"])
    try:
        return SolidMaterial(
            name=str(data.get("name", default_name)), source=str(data["source"]), **values
        )
    except ValidationError as exc:
        raise MaterialError(f"{where}: {describe(exc, _UNITS)}") from None


def load_solid_material(spec: str | Path) -> SolidMaterial:
    """The solid of ``--material NAME|FILE.toml`` with ``--object fem``.

    A file holds ``young_pa``, ``poisson``, ``density_kg_m3``, ``source`` and optionally
    ``rayleigh_alpha_per_s``, ``rayleigh_beta_s`` and ``name`` (docs/fem.md).

    Raises
    ------
    MaterialError
        Neither a preset nor a readable TOML file, or a file :func:`solid_from_mapping` refuses.
    """
    if isinstance(spec, str) and spec in SOLID_PRESETS:
        return SOLID_PRESETS[spec]
    p = Path(spec)
    if p.suffix.lower() == ".toml" or p.exists():
        data = read_toml(p, "material", MaterialError)
        return solid_from_mapping(data, str(p), default_name=p.stem)
    names = tuple(SOLID_PRESETS)
    raise MaterialError(
        f"unknown solid material {str(spec)!r}{_suggest(str(spec), names)}: give a preset "
        f"({', '.join(names)}) or a .toml file"
    )


def solid_to_params(material: SolidMaterial, base: FemParams) -> FemParams:
    """``base`` with the material's E, nu, density and damping."""
    return replace(
        base,
        young_pa=material.young_pa,
        poisson=material.poisson,
        density_kg_m3=material.density_kg_m3,
        rayleigh_alpha=material.rayleigh_alpha_per_s,
        rayleigh_beta=material.rayleigh_beta_s,
    )


if __name__ == "__main__":
    print(preset_table())
