"""What to install for an optional feature, said so that it works from a checkout and from a wheel.

The package is not on a public index, so ``pip install 'haptic-collab[fem]'`` would find nothing:
an install hint names the extra's own requirements (what ``pyproject.toml`` lists for it), which
install beside the package however it was installed, and the extra for a checkout.
"""

from __future__ import annotations

#: Each optional extra of pyproject.toml and its requirements, as listed there (checked by
#: tests/shared/test_extras.py).
EXTRAS: dict[str, tuple[str, ...]] = {
    "plots": ("matplotlib>=3.8",),
    "openhaptics": ("pyOpenHaptics>=1.0.1",),
    "forcedimension": ("forcedimension-core>=1.0",),
    "haply": ("HaplyHardwareAPI>=0.1.13",),
    "fem": ("tetgen>=0.8",),
}


def install_hint(extra: str) -> str:
    """The command that installs ``extra``'s requirements, and the extra for a checkout.

    Raises
    ------
    KeyError
        ``extra`` is not one of :data:`EXTRAS`.
    """
    reqs = " ".join(f"'{r}'" for r in EXTRAS[extra])
    return f"pip install {reqs} (the {extra} extra; in a checkout: pip install -e '.[{extra}]')"
