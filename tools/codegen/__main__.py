"""``python -m tools.codegen [--check]``: rewrite every file generated from the protocol's schema.

With ``--check`` nothing is written: the exit status is 1 when web/protocol.js or the field
reference of docs/protocol.md is stale, or a shipped gain table was made by other design code
(:mod:`tools.codegen.gain_tables`; ``make test`` runs it so).
"""

from __future__ import annotations

import sys

from tools.codegen import gain_tables, protocol_doc, protocol_js


def main(argv: list[str] | None = None) -> int:
    """Run every generator with ``argv`` (default: the command line); 1 if any file was stale."""
    args = sys.argv[1:] if argv is None else argv
    return max(protocol_js.main(args), protocol_doc.main(args), gain_tables.main(args))


if __name__ == "__main__":
    raise SystemExit(main())
