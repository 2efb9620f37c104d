"""The README's Layout names every module of the package (a new module is not left out of it)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_readme_layout_names_every_module():
    text = (ROOT / "README.md").read_text()
    layout = text[text.index("## Layout") :]
    layout = layout[: layout.index("```", layout.index("```") + 3)]
    words = set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", layout))
    missing = []
    for folder in (
        "shared",
        "server",
        "server/objects",
        "client",
        "client/devices",
        "haptic_collab",
    ):
        for path in sorted((ROOT / folder).glob("*.py")):
            if path.stem != "__init__" and path.stem not in words:
                missing.append(f"{folder}/{path.name}")
    assert missing == [], f"README Layout does not name: {missing}"
