"""Where a client's gain designs come from before the session designs any: the shipped tables
and the client's own cache.

A cell the table lacks is designed in a worker during the session: a second or more of CPU, many
seconds on a busy machine, while the contact renders interim or fallback gains that feel
different (docs/gains.md). So the session's table starts with the tables shipped for the
built-in device profiles (:func:`shared.gains.table_file.load_shipped`) and with the designs this
machine made in earlier sessions (:func:`load_cache`), and the designs of this session are added
to that cache when it ends (:func:`save_cache`). Both hold only for the design code of their
hash (:func:`shared.gains.table_file.design_code_hash`): a cache of other code is ignored, and a
new file is started beside it.

The cache is a JSON file in ``$HAPTIC_GAIN_CACHE`` (a folder), else
``$XDG_CACHE_HOME/haptic-collab``, else ``~/.cache/haptic-collab``: ``gains-<hash>.json``.
Several clients on one machine may write it: each merges what is there with its own and
replaces the file atomically.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
from dataclasses import replace
from pathlib import Path

from haptic_collab.shared.gains.key import Mode
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.table_file import (
    design_code_hash,
    load_shipped,
    load_table_document,
    ship_jobs,
    table_document,
)

log = logging.getLogger(__name__)


def cache_dir() -> Path:
    """The folder of the client's cache of designs (module docstring)."""
    env = os.environ.get("HAPTIC_GAIN_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "haptic-collab"


def cache_path(design_code: str) -> Path:
    """The cache file of the design code of hash ``design_code``."""
    return cache_dir() / f"gains-{design_code}.json"


def load_cache(table: GainTable, design_code: str) -> int:
    """Store the cached designs of ``design_code`` in ``table``; the number stored (0 without a
    cache, or with one that cannot be read: logged, never raised)."""
    path = cache_path(design_code)
    try:
        doc = json.loads(path.read_text("utf-8"))
        return load_table_document(table, doc, design_code)
    except FileNotFoundError:
        return 0
    except (OSError, ValueError) as exc:
        log.warning("gain cache %s not used: %s", path, exc)
        return 0


def save_cache(table: GainTable, design_code: str) -> int:
    """Add ``table``'s designs to the cache file (merged with what it holds now), atomically;
    the number of cells in it after, or -1 if it could not be written (logged, never raised)."""
    path = cache_path(design_code)
    merged = GainTable(table.hand_box, table.grid_ratio)
    for key, cell, design in table.cells():
        merged.store(key, cell, design)
    load_cache(merged, design_code)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(table_document(merged, design_code), f, separators=(",", ":"))
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("gain cache %s not written: %s", path, exc)
        return -1
    return len(merged)


def device_coverage(
    table: GainTable,
    *,
    k_h_max: float,
    b_h_max: float,
    mode: Mode,
    servo_rate_hz: float,
    sim_rate_hz: float,
) -> tuple[int, int]:
    """How many cells of the shipped grid (:data:`shared.gains.table_file.SHIP_GRID`) ``table``
    holds for this device [N/m, N*s/m], local model and rates [Hz]: ``(held, of)``; ``of`` is 0
    where the grid does not apply (another servo or simulation rate)."""
    keys = [
        (replace(k, mode=mode), c)
        for k, c in ship_jobs(k_h_max, b_h_max)
        if k.servo_rate_hz == servo_rate_hz and k.sim_rate_hz == sim_rate_hz
    ]
    return sum(1 for k, c in keys if table.has(k, c)), len(keys)


def preload(table: GainTable, *, cache: bool = True) -> dict[str, object]:
    """Fill ``table`` before the session's first patch: the shipped tables, then (``cache``) this
    machine's cache. Returns what was loaded, for the client's summary: ``design_code``,
    ``shipped`` ({file: cells or the reason it was refused}), ``cached`` (cells)."""
    code = design_code_hash()
    shipped = load_shipped(table, code)
    cached = load_cache(table, code) if cache else 0
    return {"design_code": code, "shipped": shipped, "cached": cached}
