"""Materials of the FEM solid (``--object fem --material NAME|FILE.toml``): SI values with sources.

A :class:`SolidMaterial` is what the elastic solid of :mod:`server.objects.fem` needs: Young's
modulus, Poisson's ratio, density and Rayleigh damping, plus where the numbers come from.
:func:`solid_to_params` turns it into :class:`~server.objects.fem.FemParams`.

Poisson's ratio: soft tissue and silicone rubber are nearly incompressible (nu about 0.49-0.5).
Linear tetrahedra lock as nu approaches 0.5 (the solid grows far too stiff), so every preset
takes nu = 0.45, the value the FEM literature on soft tissue commonly uses with P1 elements; its
half-space punch stiffness ``2 a E / (1 - nu^2)`` is 6 % below an incompressible one's.

Presets (docs/fem.md):

``liver``
    Healthy human liver, E = 5.5 kPa: transient elastography (Roulot et al. 2008 report a healthy
    range of about 2.3-5.9 kPa in their cohort; 5.5 kPa is the upper normal value used by the
    balloon's ``soft-tissue`` preset as well); density 1060 kg/m^3; Kelvin-Voigt beta 0.01 s.
``skin``
    Human skin on the forearm, E = 35 kPa: the dermis of a two-layer elastic model fitted to in
    vivo indentation (Pailler-Mattei, Bec and Zahouani 2008); density 1100 kg/m^3.
``ecoflex-0030``
    Smooth-On Ecoflex 00-30 platinum silicone (a common tissue phantom), E = 69 kPa: the 100 %
    modulus of the technical data sheet (10 psi; a secant modulus, so an upper bound at small
    strain); specific gravity 1.07.
``sylgard-184``
    Dow Sylgard 184 PDMS, 10:1 base to curing agent, cured at 25 C: E = 1.32 MPa (Johnston et al.
    2014); density 1030 kg/m^3 (data sheet). A stiff phantom: its K_o under the finger pad is
    about 50 kN/m, far beyond a desktop device, which renders it at its own limit.

References
----------
- Roulot, D., et al. (2008). Liver stiffness values in apparently healthy subjects. *Journal
  of Hepatology* 48(4), 606-613.
- Pailler-Mattei, C., Bec, S., & Zahouani, H. (2008). In vivo measurements of the elastic
  mechanical properties of human skin by indentation tests. *Medical Engineering & Physics*
  30(5), 599-606.
- Smooth-On, Ecoflex Series technical bulletin (Ecoflex 00-30: 100 % modulus 10 psi, specific
  gravity 1.07 g/cc).
- Johnston, I. D., et al. (2014). Mechanical characterization of bulk Sylgard 184 for
  microfluidics and microengineering. *J. Micromech. Microeng.* 24(3), 035017.

Nothing here uses threads, sockets or clocks.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from pydantic import ValidationError

from haptic_collab.server.materials import MaterialError, _suggest, check_table_keys
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


SOLID_PRESETS: Mapping[str, SolidMaterial] = MappingProxyType(
    {
        "liver": SolidMaterial(
            name="liver",
            young_pa=5.5e3,
            poisson=0.45,
            density_kg_m3=1060.0,
            source="transient elastography, Roulot et al. 2008 (J Hepatol 48:606)",
        ),
        "skin": SolidMaterial(
            name="skin",
            young_pa=35.0e3,
            poisson=0.45,
            density_kg_m3=1100.0,
            source="dermis, in vivo indentation, Pailler-Mattei et al. 2008 (Med Eng Phys 30:599)",
        ),
        "ecoflex-0030": SolidMaterial(
            name="ecoflex-0030",
            young_pa=69.0e3,
            poisson=0.45,
            density_kg_m3=1070.0,
            source="Smooth-On Ecoflex 00-30 data sheet, 100 % modulus 10 psi",
        ),
        "sylgard-184": SolidMaterial(
            name="sylgard-184",
            young_pa=1.32e6,
            poisson=0.45,
            density_kg_m3=1030.0,
            source="10:1, cured at 25 C, Johnston et al. 2014 (J Micromech Microeng 24:035017)",
        ),
    }
)


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
