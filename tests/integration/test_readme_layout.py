"""The Layout of docs/development.md names every module of the package (a new module is not left
out of it), and every module says in its docstring what it owns."""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE_FOLDERS = (
    "shared",
    "server",
    "server/objects",
    "client",
    "client/devices",
    "haptic_collab",
    "haptic_collab/cli",
    "haptic_collab/bench",
    "haptic_collab/research",
)


def modules() -> Iterator[tuple[str, Path]]:
    """(folder, path) of every module of the package, ``__init__`` included."""
    for folder in PACKAGE_FOLDERS:
        for path in sorted((ROOT / folder).glob("*.py")):
            yield folder, path


def test_the_readme_layout_names_every_module():
    text = (ROOT / "docs" / "development.md").read_text()
    layout = text[text.index("## Layout") :]
    layout = layout[: layout.index("```", layout.index("```") + 3)]
    words = set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", layout))
    missing = [
        f"{folder}/{path.name}"
        for folder, path in modules()
        if path.stem != "__init__" and path.stem not in words
    ]
    assert missing == [], f"docs/development.md Layout does not name: {missing}"


def test_every_module_says_what_it_owns():
    missing = []
    for folder, path in modules():
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
        if not doc or len(doc.split()) < 8:  # a sentence, not a placeholder
            missing.append(f"{folder}/{path.name}")
    assert missing == [], f"modules without a docstring saying what they own: {missing}"
