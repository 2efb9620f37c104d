"""Every ``haptic`` process runs numpy with one BLAS thread (haptic_collab.cli.blas_threads):
the gain designs of a loaded 2-core machine lost most of their time to OpenBLAS's spinning
threads, and a worker cannot lower the count after numpy is loaded."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

COUNT = "import os, sys; {imp}; import numpy; print(len(os.listdir('/proc/self/task')))"


def _threads(imp: str, env: dict[str, str]) -> int:
    out = subprocess.run(
        [sys.executable, "-c", COUNT.format(imp=imp)],
        capture_output=True, text=True, env=env, timeout=60, check=True,
    )  # fmt: skip
    return int(out.stdout.strip())


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
def test_the_haptic_command_loads_numpy_with_one_blas_thread_unless_told_otherwise() -> None:
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
    }
    assert _threads("import haptic_collab.cli", env) == 1
    if (os.cpu_count() or 1) > 1:  # what it prevents: numpy alone starts a thread per core
        assert _threads("pass", env) > 1
        # a count the user set is kept
        assert _threads("import haptic_collab.cli", {**env, "OPENBLAS_NUM_THREADS": "2"}) > 1
