"""Files generated from the protocol's schema: write one, or check that it is up to date.

Used by :mod:`tools.codegen.protocol_doc` (docs/protocol.md's field reference) and
:mod:`tools.codegen.protocol_js` (web/protocol.js); the test suite fails when either file is stale.
"""

from __future__ import annotations

import sys
from pathlib import Path


def sync_generated(path: Path, new: str, current: str | None, module: str, check: bool) -> int:
    """Write ``new`` to ``path`` unless it is already ``current``; with ``check`` only compare.

    Parameters
    ----------
    path : Path
        The generated file.
    new : str
        Its text as the generator makes it now.
    current : str or None
        Its text on disk (None: the file is missing, which is stale).
    module : str
        The generator, for the message ``PATH is stale: run python -m MODULE``.
    check : bool
        Only report: exit status 1 and the message on stderr when the file is stale.

    Returns
    -------
    int
        The exit status: 0, or 1 for a stale file under ``check``.
    """
    if check:
        if current != new:
            print(f"{path} is stale: run python -m {module}", file=sys.stderr)
            return 1
        return 0
    if current != new:
        path.write_text(new, encoding="utf-8")
        print(f"wrote {path}")
    return 0
