"""Install hints name what the index has: each extra's own requirements (shared.extras)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from haptic_collab.shared.extras import EXTRAS, install_hint

ROOT = Path(__file__).resolve().parents[2]


def test_the_extras_are_pyprojects_and_the_hint_names_their_requirements():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    for extra, reqs in EXTRAS.items():
        # the environment marker of a requirement is pyproject's business, not the hint's
        assert [r.split(";")[0].strip() for r in declared[extra]] == list(reqs), extra
        hint = install_hint(extra)
        assert all(f"'{r}'" in hint for r in reqs) and f"-e '.[{extra}]'" in hint
    # no hint names the package itself, which no public index has
    assert not re.search(r"install 'haptic-collab\[", install_hint("fem"))
