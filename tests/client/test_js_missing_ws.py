"""The Node.js client run before `make js-install` says what to run (issue 61, item 9), instead
of a stack trace ending in ERR_MODULE_NOT_FOUND."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NODE = shutil.which("node")


@pytest.mark.skipif(NODE is None, reason="node is not on PATH: the JS reference client needs it")
def test_without_its_ws_package_the_client_says_to_run_make_js_install(tmp_path):
    js = tmp_path / "js"
    shutil.copytree(ROOT / "client" / "js", js, ignore=shutil.ignore_patterns("node_modules"))
    assert NODE is not None
    res = subprocess.run(
        [NODE, str(js / "haptic-client.mjs"), "--help"],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 2
    assert "run `make js-install`" in res.stderr and "Error" not in res.stderr
