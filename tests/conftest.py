"""Test-wide set-up: each test's own caches, and the gain designs made once per test process.

**Caches.** The client keeps the gain designs it made in a cache file
(:mod:`haptic_collab.client.gain_store`) and the server keeps TetGen's volume meshes
(:mod:`haptic_collab.server.objects.volume`), both under ``~/.cache/haptic-collab`` by default.
A test run must neither read what an earlier run (or the user) left there nor leave anything:
each test gets its own empty ``HAPTIC_GAIN_CACHE`` (a client that finds a design cached renders
differently from one that must design it), and the whole run one ``XDG_CACHE_HOME`` in a
temporary folder, shared by the pytest-xdist workers and the processes the tests start, removed
at the end (volume meshes are pure functions of the surface, so sharing them is safe).

**Designs.** :func:`haptic_collab.shared.gains.table.design_cell_modes` (what
``design_cell`` and so ``GainTable.design`` run) is a pure function of its arguments (a gain
key, a cell, the grid ratio, a hand box and the local models: frozen values; the result frozen
:class:`~haptic_collab.shared.gains.design.GainDesign` values) that costs a second to a minute of
CPU. Dozens of tests design the same cells (``GainTable(...).design``, ``design_cell``); this
module replaces it, before any test module imports it, by the same function with its results
kept:

- in this process (the very object the first call returned), and
- on disk, one file per cell, in ``$HAPTIC_TEST_DESIGNS`` or ``.pytest_cache/haptic-designs``
  of this checkout, in a folder named by
  :func:`~haptic_collab.shared.gains.table_file.design_code_hash` (the code of every module a
  design runs): so pytest-xdist workers design each cell once between them (a lock file per
  cell), later runs of the same design code reuse them, and any change to that code starts an
  empty folder. A cell is read back with
  :func:`~haptic_collab.shared.gains.table_file.design_from_record`, which refuses a malformed or
  unstable record (then the cell is designed again).

**No gain table build.** A client whose device has no gain table builds one before it joins
(:mod:`haptic_collab.client.gain_build`: every cell of the shipped grid, minutes). The tests'
clients must not: ``HAPTIC_GAIN_BUILD=0`` (the default of ``ClientOptions.gain_build`` and of
``haptic client --no-gain-build``) is set for the run and every process it starts; a test of
the build passes ``gain_build=True`` itself.

Every test still gets the design the current code makes for its arguments. Processes the tests
start (``haptic server``, ``haptic client``, spawned workers) import the module afresh and design
as users' do.

**One BLAS thread.** The tests run numpy as every ``haptic`` process does: this module imports
:mod:`haptic_collab.cli.blas_threads` before anything imports numpy, so the pytest-xdist workers
and every process they start have one OpenBLAS thread (a value set in the environment is kept).
With a thread per core in each of two workers, OpenBLAS's threads spin against each other and
against the servers and browsers the tests run: one gain-check test took 29 s (26 s of CPU) on a
loaded machine against 1.7 s with one thread (2026-11-27).
"""

from __future__ import annotations

import dataclasses
import fcntl
import functools
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

import haptic_collab.cli.blas_threads  # noqa: F401  (first: before numpy is imported)
import haptic_collab.shared.gains.table as _gain_table
from haptic_collab.shared.full_loop import HandBox
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey, Mode

_ROOT = Path(__file__).resolve().parents[1]
_design_cell_modes = _gain_table.design_cell_modes


@functools.cache
def _design_dir() -> Path:
    """The folder of this design code's cells (module docstring), made if missing."""
    base = os.environ.get("HAPTIC_TEST_DESIGNS") or str(_ROOT / ".pytest_cache" / "haptic-designs")
    from haptic_collab.shared.gains.table_file import design_code_hash

    path = Path(base) / design_code_hash()
    path.mkdir(parents=True, exist_ok=True)
    return path


def _read_cell(path: Path, hand_box: HandBox) -> dict[Mode, GainDesign] | None:
    from haptic_collab.shared.gains.table_file import design_from_record

    try:
        doc = json.loads(path.read_text("utf-8"))
        return {m: design_from_record(rec, hand_box) for m, rec in doc.items()}
    except (OSError, ValueError, AttributeError):
        return None  # missing, torn or refused: designed again


@functools.cache
def _shipped(hand_box: HandBox, grid_ratio: float) -> dict[tuple[GainKey, int], GainDesign]:
    """The shipped tables' designs for this hand box and grid ratio (none when the tables are of
    another design code, hand box or ratio: ``load_shipped`` refuses them then)."""
    from haptic_collab.shared.gains.table import GainTable
    from haptic_collab.shared.gains.table_file import load_shipped

    table = GainTable(hand_box, grid_ratio)
    load_shipped(table)
    return {(k, c): d for k, c, d in table.cells()}


@functools.cache
def _kept(
    key: GainKey, cell: int, grid_ratio: float, hand_box: HandBox, modes: tuple[Mode, ...]
) -> tuple[tuple[Mode, GainDesign], ...]:
    # imported here: a broken gain_table_file fails the tests that design, not the whole run
    from haptic_collab.shared.gains.table_file import design_record

    # a cell of the shipped tables: the design this very code made for it (the tables hold the
    # design code's hash, and tools.codegen --check fails when they are stale)
    shipped = _shipped(hand_box, grid_ratio)
    found = {m: shipped.get((dataclasses.replace(key, mode=m), cell)) for m in modes}
    if all(d is not None for d in found.values()):
        return tuple((m, d) for m, d in found.items() if d is not None)

    # every field of the frozen arguments (their reprs: floats exactly), not a file's record
    what = json.dumps([repr(key), cell, repr(float(grid_ratio)), repr(hand_box), modes])
    path = _design_dir() / f"{hashlib.sha256(what.encode()).hexdigest()[:24]}.json"
    designs = _read_cell(path, hand_box)
    if designs is None:
        with open(path.with_suffix(".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # another worker designing this cell: wait for it
            designs = _read_cell(path, hand_box)
            if designs is None:
                designs = _design_cell_modes(key, cell, grid_ratio, hand_box, modes)
                fd, tmp = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
                with os.fdopen(fd, "w", encoding="utf-8") as f:
                    json.dump({m: design_record(d) for m, d in designs.items()}, f)
                os.replace(tmp, path)
    return tuple(designs.items())


@functools.wraps(_design_cell_modes)
def _kept_design_cell_modes(
    key: GainKey,
    cell: int,
    grid_ratio: float,
    hand_box: HandBox,
    modes: Sequence[Mode] = ("p", "pi"),
) -> dict[Mode, GainDesign]:
    """:func:`haptic_collab.shared.gains.table.design_cell_modes`, its results kept (module
    docstring); a new dict each call, of the same frozen designs."""
    return dict(_kept(key, cell, float(grid_ratio), hand_box, tuple(modes)))


# design_cell and the fidelity benchmark reach it through the module, so they get it too
_gain_table.design_cell_modes = _kept_design_cell_modes

_RUN_CACHE_ENV = "HAPTIC_TEST_RUN_CACHE"

# no client of the tests builds its device's gain table before joining (module docstring)
os.environ["HAPTIC_GAIN_BUILD"] = "0"

# the tests' servers tick at the ordinary policy (their in-process servers would otherwise run
# the pytest thread at SCHED_FIFO while they serve; server.priority)
os.environ.setdefault("HAPTIC_TICK_PRIORITY", "off")


def pytest_configure(config: pytest.Config) -> None:
    """One ``XDG_CACHE_HOME`` for the run: made by the first process (the xdist controller, or
    a plain pytest), inherited by its workers and every process a test starts."""
    if os.environ.get(_RUN_CACHE_ENV):
        return  # an xdist worker: the controller made it
    path = tempfile.mkdtemp(prefix="haptic-test-cache-")
    os.environ[_RUN_CACHE_ENV] = path
    os.environ["XDG_CACHE_HOME"] = path
    config.stash[_run_cache_key] = path


def pytest_unconfigure(config: pytest.Config) -> None:
    path = config.stash.get(_run_cache_key, None)
    if path is not None:
        shutil.rmtree(path, ignore_errors=True)
        os.environ.pop(_RUN_CACHE_ENV, None)


_run_cache_key = pytest.StashKey[str]()


@pytest.fixture(autouse=True)
def _own_gain_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """An empty client gain cache for each test (``HAPTIC_GAIN_CACHE``), made when first written."""
    path = tmp_path_factory.mktemp("gain-cache", numbered=True)
    old = os.environ.get("HAPTIC_GAIN_CACHE")
    os.environ["HAPTIC_GAIN_CACHE"] = str(path)
    try:
        yield path
    finally:
        if old is None:
            os.environ.pop("HAPTIC_GAIN_CACHE", None)
        else:
            os.environ["HAPTIC_GAIN_CACHE"] = old
