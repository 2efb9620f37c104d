"""One BLAS thread per ``haptic`` process, set before numpy is first imported.

OpenBLAS reads ``OPENBLAS_NUM_THREADS`` once, when it loads: a worker process that sets it later
(the gain-design workers did) keeps the threads it inherited. On a loaded 2-core machine those
threads spin: one cell's gain design took 5-15 s of wall time (2.4-7.3 s of CPU) with the
default threads against 1.0-2.6 s (0.6-1.0 s of CPU) with one, measured side by side on
2026-11-27 (docs/results/README.md). A server, a client, its servo process and the design workers
share those cores; none does linear algebra large enough to gain from threads. A value the user
set is kept. Imported first by :mod:`haptic_collab.cli`.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
