"""Reading a TOML file the server is given (its configuration, a material) with one clear error.

Its own module so that the configuration (:mod:`server.config`) and the material files
(:mod:`server.materials`, :mod:`server.solid_materials`) read files the same way without
importing each other.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any


def read_toml(path: Path, what: str, error: type[ValueError]) -> dict[str, Any]:
    """The table of TOML file ``path``; ``error`` (a ValueError) naming the file and ``what`` it
    is (``"configuration"``, ``"material"``) when it is missing, unreadable or not TOML."""
    where = str(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise error(f"{where}: {what} file does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{where}: not a valid TOML file ({exc})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{where}: cannot read the {what} file ({exc})") from None
