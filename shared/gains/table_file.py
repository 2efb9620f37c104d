"""A gain table as a file: the shipped tables and a client's own cache of designs.

A :class:`shared.gains.table.GainTable` holds full-loop designs, each a second or more of CPU
(:func:`shared.gains.table.design_cell`). Designed during a session they arrive late on a busy
machine, and meanwhile a contact renders interim or fallback gains that feel different
(docs/gains.md). Written to a file, they are designed once: offline for the built-in device
profiles (``haptic gains-table build``, shipped as package data), or by a client for itself
(its cache).

A table's file is valid only for the design code that made it: :func:`design_code_hash` hashes
the code (docstrings and comments aside) of every module a cell's design runs, and a document of
another hash is refused (:func:`load_table_document`). This module is not among them, so its
format can change without invalidating the designs; :data:`TABLE_FORMAT` says which format a
document has.

Pure but for :func:`design_code_modules` and :func:`design_code_hash`, which read the design
modules' source files.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import json
import math
import weakref
from collections.abc import Iterable, Mapping
from typing import Any

from haptic_collab.shared.full_loop import HandBox
from haptic_collab.shared.gains.damping_cover import valid_cover
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey, make_gain_key
from haptic_collab.shared.gains.policy import DESIGN_MARGIN
from haptic_collab.shared.gains.table import GainTable

#: The version of a gain table's file (:func:`table_document`): 2 since the key lost the
#: contact's dynamics.
TABLE_FORMAT = 2

#: The module whose designs a table holds: :func:`design_code_hash` starts there.
DESIGN_ROOTS = ("haptic_collab.shared.gains.table",)


def key_record(key: GainKey) -> dict[str, Any]:
    """``key`` as a JSON-ready dict (:func:`key_from_record` reads it back; a ``stiff_ratio`` of
    inf is written as the string ``"inf"``, which strict JSON can carry)."""
    return {
        "servo_rate_hz": key.servo_rate_hz,
        "sim_rate_hz": key.sim_rate_hz,
        "delay_ticks": key.delay_ticks,
        "mode": key.mode,
        "margin": key.margin,
        "k_h_max": key.k_h_max,
        "b_h_max": key.b_h_max,
        "b_o": key.b_o,
        "stiff_ratio": "inf" if math.isinf(key.stiff_ratio) else key.stiff_ratio,
        "own_force": key.own_force,
        "stiffer_by": key.stiffer_by,
    }


def key_from_record(rec: Mapping[str, Any]) -> GainKey:
    """The :class:`GainKey` :func:`key_record` wrote.

    Raises
    ------
    ValueError
        A missing field or a value of the wrong kind.
    """
    try:
        mode = rec["mode"]
        if mode not in ("p", "pi"):
            raise ValueError(f"mode must be 'p' or 'pi', got {mode!r}")
        return GainKey(
            servo_rate_hz=float(rec["servo_rate_hz"]),
            sim_rate_hz=float(rec["sim_rate_hz"]),
            delay_ticks=int(rec["delay_ticks"]),
            mode=mode,
            margin=float(rec["margin"]),
            k_h_max=float(rec["k_h_max"]),
            b_h_max=float(rec["b_h_max"]),
            b_o=float(rec["b_o"]),
            stiff_ratio=float(rec["stiff_ratio"]),
            own_force=bool(rec["own_force"]),
            stiffer_by=float(rec["stiffer_by"]),
        )
    except (KeyError, TypeError) as exc:
        raise ValueError(f"not a gain key record: {exc!r}") from None


#: The fields of :class:`GainDesign` a record carries (the hand box is the table's; the time a
#: design took is not kept).
DESIGN_FIELDS = (
    "k_h",
    "i_gain",
    "b_h",
    "proxy_hold",
    "worst_spectral_radius",
    "rho_limit",
    "felt_stiffness_ratio_1hz",
    "felt_stiffness_ratio_8hz",
    "k_o",
    "k_o_range",
    "rate_ratio",
    "delay_ticks",
    "mode",
    "own_gain",
    "scale_max",
)


def design_record(design: GainDesign) -> dict[str, Any]:
    """``design`` as a JSON-ready dict of :data:`DESIGN_FIELDS` (:func:`design_from_record`)."""
    out = {f: getattr(design, f) for f in DESIGN_FIELDS}
    out["k_o_range"] = list(design.k_o_range)
    return out


def design_from_record(rec: Mapping[str, Any], hand_box: HandBox) -> GainDesign:
    """The design :func:`design_record` wrote, for the table's ``hand_box``.

    Raises
    ------
    ValueError
        A missing field, a value of the wrong kind, gains that are not finite and >= 0 (K_h >
        0), or a worst spectral radius that is not below 1: a record that is not a stable
        design is never rendered.
    """
    try:
        hold, mode = rec["proxy_hold"], rec["mode"]
        if hold not in ("zoh", "foh") or mode not in ("p", "pi"):
            raise ValueError(f"bad proxy_hold {hold!r} or mode {mode!r}")
        lo, hi = (float(v) for v in rec["k_o_range"])
        floats = {
            f: float(rec[f])
            for f in DESIGN_FIELDS
            if f not in ("proxy_hold", "mode", "k_o_range", "rate_ratio", "delay_ticks")
        }
        d = GainDesign(
            proxy_hold=hold,
            mode=mode,
            k_o_range=(lo, hi),
            rate_ratio=int(rec["rate_ratio"]),
            delay_ticks=int(rec["delay_ticks"]),
            hand_box=hand_box,
            **floats,
        )
    except (KeyError, TypeError) as exc:
        raise ValueError(f"not a gain design record: {exc!r}") from None
    gains = (d.k_h, d.i_gain, d.b_h, d.own_gain, d.k_o, d.scale_max)
    if not (all(math.isfinite(g) and g >= 0.0 for g in gains) and d.k_h > 0.0):
        raise ValueError(f"a gain design record with gains out of range: {gains!r}")
    if not d.worst_spectral_radius < 1.0:
        raise ValueError(f"a gain design record that is not stable: {d.worst_spectral_radius!r}")
    return d


def design_code_modules(roots: Iterable[str] = DESIGN_ROOTS) -> tuple[str, ...]:
    """The modules of :mod:`haptic_collab.shared` that ``roots`` import, directly or not, and
    ``roots`` themselves, sorted (read from their source with :mod:`ast`, not imported).

    Raises
    ------
    ValueError
        A module that cannot be found.
    """
    todo, seen = list(roots), set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        for node in ast.walk(_module_ast(name)):
            if isinstance(node, ast.ImportFrom) and node.module:
                todo.append(node.module)
            elif isinstance(node, ast.Import):
                todo += [a.name for a in node.names]
        todo = [m for m in todo if m.startswith("haptic_collab.shared.")]
    return tuple(sorted(seen))


def _module_ast(name: str) -> ast.Module:
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None:
        raise ValueError(f"design module {name!r} not found")
    with open(spec.origin, "rb") as f:
        return ast.parse(f.read())


def _without_docstrings(tree: ast.Module) -> ast.Module:
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if (
                body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
    return tree


#: The module of the policy's constants (:mod:`shared.gains.policy`): only the constants the design
#: code reads from it are part of the design code's hash (:func:`_constants_read`).
CONSTANTS_MODULE = "haptic_collab.shared.gains.policy"


def _constants_read(tree: ast.Module, modules: Iterable[str]) -> ast.Module:
    """``tree`` (:data:`CONSTANTS_MODULE`'s) with only the imports and the assignments of the
    names ``modules`` import from it, and of the names those assignments use: a constant only
    the policy's choice reads (:mod:`shared.gains.choose`) does not change a design."""
    wanted: set[str] = set()
    for name in modules:
        if name == CONSTANTS_MODULE:
            continue
        for node in ast.walk(_module_ast(name)):
            if isinstance(node, ast.ImportFrom) and node.module == CONSTANTS_MODULE:
                wanted |= {a.name for a in node.names}

    def targets(node: ast.stmt) -> set[str]:
        if isinstance(node, ast.Assign):
            return {t.id for t in node.targets if isinstance(t, ast.Name)}
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            return {node.target.id}
        return set()

    grew = True
    while grew:  # the names the wanted assignments use, until none is added
        grew = False
        for node in tree.body:
            if targets(node) & wanted:
                used = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)} - wanted
                if used:
                    wanted |= used
                    grew = True
    body = [
        n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom) or targets(n) & wanted
    ]
    return ast.Module(body=body or [ast.Pass()], type_ignores=[])


def design_code_hash(roots: Iterable[str] = DESIGN_ROOTS) -> str:
    """16 hex digits of SHA-256 over the code of :func:`design_code_modules` (their syntax
    trees without docstrings; comments and formatting never reach the tree; of
    :data:`CONSTANTS_MODULE`, only the constants the design reads): a gain table's
    file holds for the design code of this hash only. ``tools/codegen --check`` checks the
    shipped tables with it; a client's cache of designs is keyed by it. Computed once per
    process and set of roots (the source files are read once: parsing them is a few tenths of
    a second, which every client's start and every session's table would pay again).

    Raises
    ------
    ValueError
        As :func:`design_code_modules`.
    """
    return _design_code_hash(tuple(roots))


@functools.cache
def _design_code_hash(roots: tuple[str, ...]) -> str:
    h = hashlib.sha256()
    modules = design_code_modules(roots)
    for name in modules:
        tree = _without_docstrings(_module_ast(name))
        if name == CONSTANTS_MODULE:
            tree = _constants_read(tree, modules)
        dump = ast.dump(tree, include_attributes=False)
        h.update(name.encode() + b"\0" + dump.encode() + b"\0")
    return h.hexdigest()[:16]


#: The module of the damping coverage check (:mod:`shared.gains.damping_cover`):
#: :func:`cover_code_hash` starts there.
COVER_ROOTS = ("haptic_collab.shared.gains.damping_cover",)


@functools.cache
def cover_code_hash() -> str:
    """:func:`design_code_hash` of the damping coverage check (:data:`COVER_ROOTS`: the check,
    the full loop it runs and the lattice it reads, :data:`shared.gains.policy.B_O_COVER_LATTICE`):
    a table's ``b_o_covered`` holds for the check of this hash only. Computed once per process
    (the source files are read once)."""
    return design_code_hash(COVER_ROOTS)


def cover_header(cover_code: str) -> dict[str, Any]:
    """A table document's ``damping_cover`` entry: the cover code's hash and the lattice [N/m]."""
    from haptic_collab.shared.gains.policy import B_O_COVER_LATTICE

    return {"code": cover_code, "lattice": list(B_O_COVER_LATTICE)}


def cover_is_fresh(doc: Mapping[str, Any], cover_code: str) -> bool:
    """Whether ``doc``'s ``b_o_covered`` values were made by the check of hash ``cover_code``."""
    head = doc.get("damping_cover")
    return isinstance(head, Mapping) and head.get("code") == cover_code


#: What a shipped table covers, for each built-in profile: the servo rate [Hz], the simulation
#: rates [Hz], the loop delays [ticks], the coupling classes (K_o_stiff / K_o_eff), the K_o range
#: [N/m] (every grid cell from the one holding the lower end to the one holding the upper), both
#: local models, the product's design margin, an object without damping (B_o 0: the balloon and
#: any mesh; the FEM solid reports B_o and is designed during the session). The coupling classes
#: go up to 16 because two users' contacts on real meshes reach them (the torus 2.33, the bowl
#: 12.2: docs/gains.md, "Why classes up to 16"); a key beyond is designed during the session.
#: K_o goes down to 5 N/m for the FEM solid's soft spots (the bowl's rim 9.2 N/m, a bunny's 7 N/m:
#: docs/gains.md, "Why down to 5 N/m").
SHIP_GRID: dict[str, Any] = {
    "servo_rate_hz": 1000.0,
    "sim_rate_hz": (20.0,),
    "delay_ticks": tuple(range(0, 6)),
    "stiff_ratio": (1.0, math.sqrt(2.0), 2.0, 2.0 * math.sqrt(2.0), 4.0, 8.0, 16.0),
    "k_o_n_per_m": (5.0, 2000.0),
    "margin": DESIGN_MARGIN,
}


def ship_jobs(
    k_h_max: float, b_h_max: float, grid: dict[str, Any] = SHIP_GRID
) -> list[tuple[GainKey, int]]:
    """The (key, cell) of a table for a device of these limits [N/m, N*s/m], P keys (each job
    designs both local models), the cells around the default balloon's K_o (300 N/m) first."""
    table = GainTable()
    lo, hi = grid["k_o_n_per_m"]
    cells = range(table.cell(lo), table.cell(hi) + 1)
    mid = table.cell(300.0)
    jobs = [
        (
            make_gain_key(
                servo_rate_hz=grid["servo_rate_hz"],
                sim_rate_hz=rate,
                delay_ticks=d,
                mode="p",
                margin=grid["margin"],
                k_h_max=k_h_max,
                b_h_max=b_h_max,
                b_o=0.0,
                stiff_ratio=sr,
            ),
            c,
        )
        for rate in grid["sim_rate_hz"]
        for d in grid["delay_ticks"]
        for sr in grid["stiff_ratio"]
        for c in cells
    ]
    # the balloon's neighbourhood (+-4 cells, 200-450 N/m) at every delay and class first
    jobs.sort(
        key=lambda j: (abs(j[1] - mid) > 4, j[0].delay_ticks, j[0].stiff_ratio, abs(j[1] - mid))
    )
    return jobs


#: Each table's damping coverage: ``{(key, cell): (b_o_covered, design)}`` [N/m] of its designs
#: for B_o = 0 that a shipped table checked on damped objects (:mod:`shared.gains.damping_cover`),
#: with the very design object checked: a design stored over it later (another build's) has no
#: coverage. Kept beside the table, not in it: :class:`shared.gains.table.GainTable` is design
#: code (:func:`design_code_hash` hashes it), and the coverage is not. Filled by
#: :func:`load_table_document`; read by :func:`b_o_covered`.
_COVERS: weakref.WeakKeyDictionary[
    GainTable, dict[tuple[GainKey, int], tuple[float, GainDesign]]
] = weakref.WeakKeyDictionary()


def b_o_covered(table: GainTable, key: GainKey, cell: int) -> float:
    """The object damping B_o [N/m] up to which ``table``'s design of ``cell`` of ``key`` (a key
    with B_o = 0) passed its check on the damped loop (:func:`shared.gains.damping_cover.covered_b_o`);
    0 where it was not checked (a design made during a session, a cache's, a stale coverage, or a
    design stored over the one checked) or passed at no B_o of the lattice."""
    got = _checked_cover(table, key, cell)
    return 0.0 if got is None else got


def _checked_cover(table: GainTable, key: GainKey, cell: int) -> float | None:
    """The coverage [N/m] the check found for the very design ``table`` holds for ``cell`` of
    ``key`` (0 included), or None where that design was not checked."""
    got = _COVERS.get(table, {}).get((key, cell))
    if got is None:
        return None
    cover, design = got
    return cover if _stored(table, key, cell) is design else None


def _stored(table: GainTable, key: GainKey, cell: int) -> GainDesign | None:
    """The design object ``table`` holds for ``cell`` of ``key`` (not :meth:`GainTable.lookup`'s
    copy scaled to a K_o): its own ``_cells``, read here because the table's module is design code
    whose hash a new method would change."""
    return table._cells.get((key, cell))


def set_b_o_covered(table: GainTable, key: GainKey, cell: int, b_o: float) -> None:
    """Record ``b_o`` [N/m] as the coverage the check found for ``table``'s design of ``cell``
    of ``key`` (:func:`b_o_covered`; 0: checked, and it passed at no B_o of the lattice).

    Raises
    ------
    ValueError
        As :func:`shared.gains.damping_cover.valid_cover`, or a ``key`` with B_o > 0.
    """
    v = valid_cover(b_o)
    if key.b_o != 0.0:
        raise ValueError(f"a coverage is of a design for B_o = 0, got a key of B_o {key.b_o!r}")
    covers = _COVERS.setdefault(table, {})
    design = _stored(table, key, cell)
    if design is not None:
        covers[(key, cell)] = (v, design)
    else:
        covers.pop((key, cell), None)


def table_document(table: GainTable, design_code: str) -> dict[str, Any]:
    """``table``'s designs as a JSON-ready document: its format, the design code's hash
    (:func:`design_code_hash`), the hand box and grid ratio the designs hold for, and one record
    per cell (:func:`key_record`, :func:`design_record`), sorted so that the same designs give
    the same document. A cell's ``b_o_covered`` is written only where its design was checked
    (:func:`set_b_o_covered`), so that a design added after the coverage was found (a wider
    grid built into a covered table) is checked by the next pass rather than read as covering
    nothing."""
    covers = _COVERS.get(table, {})
    cells: list[dict[str, Any]] = []
    for k, c, d in table.cells():
        rec: dict[str, Any] = {"key": key_record(k), "cell": c, "design": design_record(d)}
        cover = _checked_cover(table, k, c)
        if cover is not None:
            rec["b_o_covered"] = cover
        cells.append(rec)
    cells.sort(key=lambda r: (json.dumps(r["key"], sort_keys=True), r["cell"]))
    doc: dict[str, Any] = {
        "format": TABLE_FORMAT,
        "design_code": design_code,
        "hand_box": repr(table.hand_box),
        "grid_ratio": table.grid_ratio,
        "cells": cells,
    }
    if covers:
        doc["damping_cover"] = cover_header(cover_code_hash())
    return doc


def load_table_document(table: GainTable, doc: Any, design_code: str) -> int:
    """Store the cells of ``doc`` (:func:`table_document`) in ``table``; the number stored.

    Cells ``table`` has already are kept as they are. A cell's ``b_o_covered`` [N/m] (a shipped
    table's: :mod:`shared.gains.damping_cover`) is recorded for ``table``
    (:func:`b_o_covered`) when the document's ``damping_cover`` names this cover code
    (:func:`cover_code_hash`); a coverage of another check code is dropped, its designs kept.

    Raises
    ------
    ValueError
        ``doc`` is of another format, design code, hand box or grid ratio than ``table`` and
        ``design_code``, or a record is malformed (a ``b_o_covered`` that is NaN, negative,
        infinite or not a number included, whatever its cover code: a corrupted file): nothing
        is stored then.
    """
    if not isinstance(doc, Mapping):
        raise ValueError("a gain table document is a JSON object")
    if doc.get("format") != TABLE_FORMAT:
        raise ValueError(f"gain table format {doc.get('format')!r}, expected {TABLE_FORMAT}")
    if doc.get("design_code") != design_code:
        raise ValueError(
            f"gain table of design code {doc.get('design_code')!r}, this code is {design_code!r}"
        )
    if doc.get("hand_box") != repr(table.hand_box):
        raise ValueError("gain table made for another hand box")
    if doc.get("grid_ratio") != table.grid_ratio:
        raise ValueError(f"gain table of grid ratio {doc.get('grid_ratio')!r}")
    cells = doc.get("cells")
    if not isinstance(cells, list):
        raise ValueError("a gain table document's cells are a list")
    head = doc.get("damping_cover")
    if head is not None and not (isinstance(head, Mapping) and isinstance(head.get("code"), str)):
        raise ValueError(f"a gain table's damping_cover is {{code, lattice}}, got {head!r}")
    # a coverage of another check code or lattice is not used (the designs still are)
    fresh = head is not None and head.get("code") == cover_code_hash()
    parsed = []
    for rec in cells:
        if not isinstance(rec, Mapping):
            raise ValueError("a gain table cell is a JSON object")
        key = key_from_record(rec.get("key", {}))
        cell = rec.get("cell")
        if not isinstance(cell, int) or isinstance(cell, bool):
            raise ValueError(f"a gain table cell's index is an integer, got {cell!r}")
        cover: float | None = None
        if "b_o_covered" in rec:
            try:
                cover = valid_cover(rec["b_o_covered"])
            except ValueError as exc:
                raise ValueError(f"gain table cell {cell} of {key}: {exc}") from None
            if cover > 0.0 and key.b_o != 0.0:
                raise ValueError(f"gain table cell {cell} of {key}: a coverage of a damped key")
        design = design_from_record(rec.get("design", {}), table.hand_box)
        parsed.append((key, cell, design, cover if fresh and key.b_o == 0.0 else None))
    added = 0
    for key, cell, design, cover in parsed:
        if not table.has(key, cell):
            table.store(key, cell, design)
            added += 1
            if cover is not None:
                set_b_o_covered(table, key, cell, cover)
    return added


#: The package folder of the shipped tables (one ``<profile>.json`` per built-in profile, made by
#: ``haptic gains-table --ship``).
SHIPPED_PACKAGE = "haptic_collab.shared.gains.tables"


def load_shipped(table: GainTable, design_code: str | None = None) -> dict[str, int | str]:
    """Load every shipped table (:data:`SHIPPED_PACKAGE`) into ``table``: ``{file: cells
    stored}``, or ``{file: reason}`` for a file refused (another design code or hand box, or
    malformed). Never raises for a bad file: a session without a shipped table designs its
    cells as before. Reads package data."""
    import importlib.resources

    code = design_code_hash() if design_code is None else design_code
    out: dict[str, int | str] = {}
    try:
        files = sorted(
            (
                f
                for f in importlib.resources.files(SHIPPED_PACKAGE).iterdir()
                if f.name.endswith(".json")
            ),
            key=lambda f: f.name,
        )
    except (ModuleNotFoundError, FileNotFoundError, NotADirectoryError):
        return out
    for f in files:
        try:
            out[f.name] = load_table_document(table, json.loads(f.read_text("utf-8")), code)
        except (ValueError, OSError) as exc:  # json.JSONDecodeError is a ValueError
            out[f.name] = str(exc)
    return out
