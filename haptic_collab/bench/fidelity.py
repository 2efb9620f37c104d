"""``haptic bench fidelity``: every rendering scheme side by side, in one run (README, "Fidelity").

A *condition* is an object model x K_o x simulation rate x one-way delay. In each, every scheme
of :data:`haptic_collab.research.fidelity_schemes.SCHEMES` runs on the vectorised 1-D multirate model of
:mod:`haptic_collab.research.fidelity_1d` with every hand of the box (and, reported apart, hands outside it) on every
trajectory, and with the probe as a position source at each frequency of :data:`FELT_HZ` (the
felt impedance). The local models render the product's own design
(:class:`shared.gains.table.GainTable`, the client's key), made for the K_o the simulation
reports. Each peer picks its tuning as its user must, without knowing the object: on the spring
of the K_o reported (the nominal object), at that rate, delay and user count, every tuning of its
sweep (:func:`haptic_collab.research.fidelity_schemes.peer_renderings`) runs, and the one stable
with every hand of the box, then felt closest (:func:`choose_variant`), is the one judged on every
object of that K_o, rate and delay.

The two-user grid (``two_users``) runs every condition again with another user pressing and
letting go on the same object (:class:`haptic_collab.research.fidelity_cases.OtherUser`: the rest
surface under the user moves; no rest plane is sent), the same hands and trajectories, and ranks
the schemes by how a user held still follows the other's press
(:func:`haptic_collab.research.fidelity_ranking.follow_error`); it is summarised apart
(``summary["two_users"]``, ``conditions_two_users``).

The objects (:data:`haptic_collab.research.fidelity_cases.OBJECTS`): ``spring`` is the model the product's design
assumes; ``spring-0.8`` / ``spring-1.2`` (K_o reported 25 % high / 17 % low), ``sls``
(viscoelastic, with mass) and ``stiffening`` are objects it did not see.

Ranking (:func:`rank`, :mod:`haptic_collab.research.fidelity_ranking`): with every hand of the box in the loop, a scheme counts in a condition
only if it is stable with every hand on every trajectory; its felt error is the largest
``|ln |q(f)||`` over :data:`haptic_collab.research.fidelity_ranking.BAND_HZ`, ``q`` the felt dynamic stiffness over the object's own;
the best is the smallest, and every scheme within the stiffness JND of it
(:data:`STIFFNESS_JND`: ``error <= best + ln(1 + JND)``) is tied with it. The same ranking is
also made per hand (a scheme stable with that hand on that trajectory).

``--quick`` runs :data:`QUICK_GRID`; :data:`FULL_GRID` is the whole grid. ``--plot DIR`` writes
``fidelity-stability.png`` and ``fidelity-transparency.png``.

This module reads a clock only to report wall time.
"""

from __future__ import annotations

import itertools
import math
import multiprocessing as mp
import os
import statistics
import time
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from haptic_collab.research.fidelity_1d import simulate
from haptic_collab.research.fidelity_cases import (
    FELT_RETRY_EXTRA_S,
    FELT_SETTLE_S,
    FELT_SINE_START_S,
    FOLLOW_WINDOWS_S,
    OBJECTS,
    OTHER_USER,
    OTHER_USER_FOLLOW,
    TRAJECTORIES,
    Cell,
    ObjectModel,
    Run,
    RunOptions,
    felt_depth_m,
    felt_trajectory,
    follow_depth_m,
    follow_trajectory,
)
from haptic_collab.research.fidelity_metrics import cell_metrics, felt_response
from haptic_collab.research.fidelity_ranking import (
    FELT_HZ,
    STIFFNESS_JND,
    Outcome,
    choose_variant,
    follow_error,
    rank,
    scheme_record,
    summarize,
)
from haptic_collab.research.fidelity_schemes import (
    LOCAL_MODELS,
    SCHEMES,
    DeviceModel,
    Rendering,
    TableCell,
    design_delay_ticks,
    peer_renderings,
    rendering_for,
    scheme_tuning,
)
from haptic_collab.shared.full_loop import (
    DEFAULT_HAND,
    DEFAULT_HAND_BOX,
    Hand,
)
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey, Mode
from haptic_collab.shared.gains.policy import DESIGN_MARGIN, STIFFER_BY
from haptic_collab.shared.gains.policy import HOLD_BACK_S as REST_HOLD_BACK_S
from haptic_collab.shared.gains.table import GainTable, design_cell, design_cell_modes
from haptic_collab.shared.gains.verified_plane import (
    checked_plane,
    felt_closer,
    plane_applies,
    verified_plane,
)

__all__ = [
    "DEVICE",
    "FIDELITY_MESHES_3D",
    "FULL_GRID",
    "GRID_HANDS",
    "OUTSIDE_HANDS",
    "QUICK_GRID",
    "Grid",
    "plot",
    "run",
]

_OBJECTS = {o.name: o for o in OBJECTS}
_TRAJ = {t.name: t for t in TRAJECTORIES}
_SERVO_RATE_HZ = 1000.0
_BATCH = 4000


@dataclass(frozen=True)
class Grid:
    """The conditions every scheme runs on (SI units; delays in ms, one way).

    ``objects`` names models of :data:`haptic_collab.research.fidelity_cases.OBJECTS`; ``hands`` are the hand box's
    (the ranking's), ``outside_hands`` are run and reported apart (not a claim of the product).
    """

    k_o: tuple[float, ...]
    sim_rate_hz: tuple[float, ...]
    delay_ms: tuple[float, ...]
    hands: tuple[Hand, ...]
    trajectories: tuple[str, ...] = tuple(t.name for t in TRAJECTORIES)
    objects: tuple[str, ...] = tuple(o.name for o in OBJECTS)
    outside_hands: tuple[Hand, ...] = ()

    def __post_init__(self) -> None:
        for name in self.objects:
            if name not in _OBJECTS:
                raise ValueError(
                    f"unknown object model {name!r}; expected one of {sorted(_OBJECTS)}"
                )
        for name in self.trajectories:
            if name not in _TRAJ:
                raise ValueError(f"unknown trajectory {name!r}; expected one of {sorted(_TRAJ)}")

    def as_dict(self) -> dict[str, Any]:
        """The grid, JSON-ready."""
        return {
            "k_o_n_per_m": list(self.k_o),
            "sim_rate_hz": list(self.sim_rate_hz),
            "delay_ms": list(self.delay_ms),
            "hands": [h.as_dict() for h in self.hands],
            "outside_hands": [h.as_dict() for h in self.outside_hands],
            "trajectories": list(self.trajectories),
            "objects": list(self.objects),
        }


#: The hands: the 8 corners of the full-loop hand box and the default simulated hand.
GRID_HANDS: tuple[Hand, ...] = (*DEFAULT_HAND_BOX.corners(), DEFAULT_HAND)

#: Hands outside the design's box (reported apart): a stiff grip, a light fingertip hold, a
#: lightly damped device held loosely.
OUTSIDE_HANDS: tuple[Hand, ...] = (
    Hand(mass_kg=0.6, damping_n_s_per_m=10.0, stiffness_n_per_m=3000.0),
    Hand(mass_kg=0.05, damping_n_s_per_m=2.0, stiffness_n_per_m=20.0),
    Hand(mass_kg=0.3, damping_n_s_per_m=0.5, stiffness_n_per_m=300.0),
)

#: The whole grid.
FULL_GRID = Grid(
    k_o=(100.0, 300.0, 1000.0, 3000.0),
    sim_rate_hz=(10.0, 20.0, 50.0, 100.0),
    delay_ms=(0.0, 10.0, 50.0, 100.0, 200.0),
    hands=GRID_HANDS,
    outside_hands=OUTSIDE_HANDS,
)

#: ``--quick``: the softest-but-one and stiffest objects, the paper's 20 Hz and a fast 50 Hz, no
#: delay, a LAN-like 10 ms and a long 100 ms; every object model, hand of the box and trajectory.
QUICK_GRID = Grid(
    k_o=(300.0, 3000.0),
    sim_rate_hz=(20.0, 50.0),
    delay_ms=(0.0, 10.0, 100.0),
    hands=GRID_HANDS,
)

#: The device of every cell (the simulated Phantom Desktop).
DEVICE = DeviceModel()

#: Stress-set shapes (:mod:`server.objects.shapes`) whose top a user presses in the 3-D cells,
#: besides the balloon: a flat face with sharp edges, a thin part, a genus-1 ring, and the box as
#: a FEM solid (liver-like, :data:`haptic_collab.research.harness_3d.FEM_MATERIAL_3D`).
FIDELITY_MESHES_3D = ("box", "plate", "torus", "fem:box")


def _gain_key(
    mode: str,
    sim_rate_hz: float,
    delay_ms: float,
    device: DeviceModel,
    b_o: float = 0.0,
    *,
    margin: float = DESIGN_MARGIN,
    stiffer_by: float = STIFFER_BY,
) -> GainKey:
    """The key the product's client builds: B_o [N/m] quantized down as ``make_gain_key`` does; ``margin`` and ``stiffer_by`` the product's unless a run
    asks for others (``run``)."""
    return GainKey(
        servo_rate_hz=_SERVO_RATE_HZ,
        sim_rate_hz=sim_rate_hz,
        delay_ticks=design_delay_ticks(delay_ms * 1e-3, sim_rate_hz),
        mode="pi" if mode == "pi" else "p",
        margin=margin,
        k_h_max=device.max_stiffness_n_per_m,
        b_h_max=device.max_damping_n_s_per_m,
        b_o=float(math.floor(max(0.0, b_o))),
        stiffer_by=stiffer_by,
    )


def _reported_b_o(name: str, k_o: float, sim_rate_hz: float) -> float:
    """The B_o [N/m] the simulation reports for object ``name`` (its one-tick stiffness less the
    static one, as the product's World reports it), quantized as the client's key does."""
    return float(math.floor(_OBJECTS[name].reported_b_o(k_o, sim_rate_hz)))


def _k_o_designed(obj: ObjectModel, k_o: float, reached: bool) -> list[float]:
    """The K_o [N/m] whose gain-table cells the run designs for ``obj`` reported at ``k_o``:
    ``k_o``, and with ``reached`` one K_o in each cell above it up to the K_o the object reports
    at the trajectories' held depth (the middle of each cell)."""
    ks = [k_o]
    if reached:
        table = GainTable()
        top = obj.reported_k_o(k_o, max(t.y1_m for t in TRAJECTORIES))
        r = table.grid_ratio
        ks += [
            table.grid_point(c) * math.sqrt(r)
            for c in range(table.cell(k_o) + 1, table.cell(top) + 1)
        ]
    return ks


def _design_cost(job: tuple[str, GainKey, float]) -> tuple[float, float]:
    """A design job's relative cost, for ordering: N (N + delay ticks)^3, PI before P."""
    mode, key, _ = job
    n = key.rates.ratio
    return (float(n * (n + key.delay_ticks) ** 3), 1.0 if mode == "pi" else 0.0)


def _plane_cell(key: GainKey, k_o: float, design: GainDesign | None) -> GainDesign | None:
    """The verified plane of the client's gain-table cell holding K_o under ``key`` where it is
    felt closer to the object than ``design`` (that cell's, or the design of the cell of the K_o
    reported where K_o is a stiffness the own-response check identified; a worker's job;
    :func:`shared.gains.verified_plane.verified_plane`), or None."""
    table = GainTable(DEFAULT_HAND_BOX)
    return verified_plane(key, table.cell(k_o), table.grid_ratio, table.hand_box, design)


def _plane_check_key(key: GainKey, k_o: float) -> tuple[GainKey, int]:
    """What a plane's check depends on: the key but its local model, and the cell of K_o."""
    return replace(key, mode="p"), GainTable(DEFAULT_HAND_BOX).cell(k_o)


def _checked_plane_cell(key: GainKey, k_o: float) -> GainDesign | None:
    """The plane of the client's gain-table cell holding K_o under ``key`` that passes its
    check, before any comparison with a design (a worker's job;
    :func:`shared.gains.verified_plane.checked_plane`), or None."""
    table = GainTable(DEFAULT_HAND_BOX)
    return checked_plane(key, table.cell(k_o), table.grid_ratio, table.hand_box)


def _closer(plane: GainDesign | None, key: GainKey, design: GainDesign) -> GainDesign | None:
    """``plane`` where it is felt closer to the object than ``design`` under ``key``
    (:func:`shared.gains.verified_plane.felt_closer`), else None."""
    return plane if plane is not None and felt_closer(plane, key, design) else None


#: What a job is held against: a design, or the key of the design it will be.
_D = TypeVar("_D")


def _keyed_by(name: str, key: GainKey, k_o: float) -> bool:
    """Whether object ``name`` reported at ``k_o`` [N/m] gives the client ``key``'s B_o (the
    springs and the stiffening object share their keys; the viscoelastic object's are its own)."""
    return _reported_b_o(name, k_o, key.sim_rate_hz) == key.b_o


def _identified_plane_jobs(
    designs: Mapping[tuple[str, GainKey, float], _D],
    objects: Sequence[str],
    k_os: Sequence[float],
) -> dict[tuple[str, GainKey, float], tuple[GainKey, float, _D]]:
    """The plane checks a client makes once its own-response check identifies an object
    ``error`` times the K_o reported (:func:`shared.gains.own_response.identify`), ``error`` the
    stiffness error of an object of ``objects`` that gives that key (:func:`_keyed_by`): for
    each design of a K_o of ``k_os`` whose key allows a plane, ``(mode, key, error K_o)`` ->
    ``(key, error K_o, that design)``, the plane of the identified stiffness's cell checked
    against the design of the cell reported (:func:`_plane_cell`)."""
    return {
        (w[0], w[1], e * w[2]): (w[1], e * w[2], d)
        for w, d in sorted(designs.items(), key=lambda kv: str(kv[0]))
        if plane_applies(w[1]) and w[2] in k_os
        for e in sorted(
            {_OBJECTS[n].stiffness_error for n in objects if _keyed_by(n, w[1], w[2])} - {1.0}
        )
    }


def _alone_plane_jobs(
    designs: Mapping[tuple[str, GainKey, float], object],
    objects: Sequence[str],
    k_os: Sequence[float],
) -> dict[tuple[str, GainKey, float], tuple[GainKey, float]]:
    """The planes a client checks alone: for each design of a grid K_o of ``k_os`` whose key
    allows a plane, ``(mode, key, K)`` -> ``(key, K)`` for each K (the middle of a cell) that an
    object of ``objects`` giving that key (:func:`_keyed_by`) reports on the way to the
    trajectories' held depth and that
    ``designs`` has no design for (:func:`_k_o_designed`: the stiffening object's cells above
    the K_o reported at rest)."""
    return {
        (mode, key, k): (key, k)
        for (mode, key, k_o) in sorted(designs, key=str)
        if plane_applies(key) and k_o in k_os
        for name in objects
        if _keyed_by(name, key, k_o)
        for k in _k_o_designed(_OBJECTS[name], k_o, True)[1:]
        if (mode, key, k) not in designs
    }


def _design_cell(key: GainKey, k_o: float) -> GainDesign:
    """The design of the client's gain-table cell holding K_o under ``key`` (a worker's job),
    unscaled (:func:`shared.gains.table.design_cell`)."""
    table = GainTable(DEFAULT_HAND_BOX)
    return design_cell(key, table.cell(k_o), table.grid_ratio, table.hand_box)


def _design_cells(key: GainKey, k_o: float, modes: tuple[Mode, ...]) -> dict[Mode, GainDesign]:
    """:func:`_design_cell` of ``key`` with each local model of ``modes``, ``{mode: design}``,
    their common candidates searched once (a worker's job;
    :func:`shared.gains.table.design_cell_modes`)."""
    table = GainTable(DEFAULT_HAND_BOX)
    return design_cell_modes(key, table.cell(k_o), table.grid_ratio, table.hand_box, modes)


def _design(key: GainKey, k_o: float) -> GainDesign:
    """The design the product's client renders for K_o under ``key``: its cell's, scaled to K_o
    (:meth:`shared.gains.table.GainTable.lookup`)."""
    return _design_cell(key, k_o).at(k_o)


def _table(
    designs: dict[tuple[str, GainKey, float], GainDesign], mode: str, key: GainKey
) -> tuple[TableCell, ...]:
    """The cells the run designed for ``(mode, key)``: the client's gain table for that key."""
    t = GainTable(DEFAULT_HAND_BOX)
    return tuple(
        TableCell.from_design(t.cell(k_o), d, t.grid_ratio)
        for (m, k, k_o), d in sorted(designs.items(), key=lambda kv: kv[0][2])
        if m == mode and k == key
    )


def _planes(
    planes: dict[tuple[str, GainKey, float], GainDesign | None], mode: str, key: GainKey
) -> tuple[TableCell, ...]:
    """The verified planes the run found for ``(mode, key)``'s cells, as table cells."""
    t = GainTable(DEFAULT_HAND_BOX)
    return tuple(
        TableCell.from_design(t.cell(k_o), d, t.grid_ratio)
        for (m, k, k_o), d in sorted(planes.items(), key=lambda kv: kv[0][2])
        if m == mode and k == key and d is not None
    )


def _plane_json(plane: GainDesign | None, k_o: float) -> dict[str, Any] | None:
    """A verified plane as the JSON's ``gains`` record gives it (None: none, or none passed)."""
    if plane is None:
        return None
    p = plane.at(k_o)
    return {"k_h": p.k_h, "b_h": p.b_h, "own_gain": p.own_gain, "proxy_hold": p.proxy_hold}


def _follow_errors(run: Run, cells: Sequence[Cell]) -> list[float]:
    """The follow error (:func:`haptic_collab.research.fidelity_ranking.follow_error`) of each
    follow probe of a run (:func:`haptic_collab.research.fidelity_cases.follow_trajectory`):
    the mean force before, while and after the other user holds (:data:`FOLLOW_WINDOWS_S`)
    against the relaxed object's own rise at the probe's depth; ``inf`` for a runaway."""
    out = []
    for i, c in enumerate(cells):
        if c.other is None or c.hand is not None:
            raise ValueError("a follow probe is a position source with another user")
        f = run.f[i]
        means = []
        for lo, hi in FOLLOW_WINDOWS_S:
            m = (run.t >= lo - 1e-9) & (run.t < hi - 1e-9)
            means.append(float(np.mean(f[m])))
        lo, hi = FOLLOW_WINDOWS_S[1]
        held = (run.t >= lo - 1e-9) & (run.t < hi - 1e-9)
        depth = c.trajectory.y1_m
        rise = float(
            c.obj.static_force_n(c.k_o, depth + c.other.bulge_m)
            - c.obj.static_force_n(c.k_o, depth)
        )
        ripple = float(np.ptp(f[held]))
        before, during, after = means
        err = math.inf if run.runaway[i] else follow_error(before, during, after, rise, ripple)
        out.append(err)
    return out


def _simulate_batch(
    cells: list[Cell], felt: bool | str, device: DeviceModel, options: RunOptions
) -> list[Any]:
    """Simulate one batch (a worker's job): metrics, felt responses ``(|q|, arg q)`` (``felt``
    True) or follow errors (``felt`` ``"follow"``)."""
    run = simulate(cells, device=device, servo_rate_hz=_SERVO_RATE_HZ, options=options)
    if felt == "follow":
        return _follow_errors(run, cells)
    if felt:
        return [
            None if q is None else (abs(q), math.atan2(q.imag, q.real))
            for q in felt_response(run, cells)
        ]
    return [m.to_json() for m in cell_metrics(run, cells)]


def _run_outcomes(
    pool: Executor,
    entries: Sequence[tuple[int, bool, str, float, float, float]],
    outcomes: list[Outcome],
    *,
    hands: Sequence[Hand],
    n_box: int,
    trajectories: Sequence[str],
    device: DeviceModel,
    options: RunOptions,
    both_phases: bool,
) -> tuple[int, int, int]:
    """Simulate every cell of ``entries`` (``(outcome id, two users, object, K_o, rate,
    delay)``) in the pool and fill in their outcomes: each rendering with every hand of
    ``hands`` (the first ``n_box`` the box's; with another user the box's only) on every
    trajectory, at both ends of the sampling phase (``both_phases``); alone, the felt probes
    (measured again on the longer probe where not read and the rendering is box-stable); with
    another user, the follow probe. Returns the cells simulated, the felt probes measured again
    and those of them read."""
    hand_cells: dict[str, list[tuple[int, int, int, Cell]]] = defaultdict(list)
    stale_cells: list[tuple[int, int, int, Cell]] = []
    felt_cells: dict[float, list[tuple[int, Cell]]] = defaultdict(list)
    follow_cells: list[tuple[int, Cell]] = []
    for oid, two, name, k_o, rate, d in entries:
        r = outcomes[oid].rendering
        obj = _OBJECTS[name]
        other = OTHER_USER if two else None
        for ti, tr in enumerate(trajectories):
            for hi, h in enumerate(hands[:n_box] if two else hands):
                cell = Cell(r, k_o, rate, d, h, _TRAJ[tr], obj, other=other)
                hand_cells[tr].append((oid, ti, hi, cell))
                if both_phases:
                    stale_cells.append((oid, ti, hi, replace(cell, stale_sample=True)))
        if two:
            depth = follow_depth_m(k_o, device.max_force_n, obj, OTHER_USER_FOLLOW.bulge_m)
            cell = Cell(r, k_o, rate, d, None, follow_trajectory(depth), obj,
                        other=OTHER_USER_FOLLOW)  # fmt: skip
            follow_cells.append((oid, cell))
            continue
        depth = felt_depth_m(k_o, device.max_force_n, obj)
        for hz in FELT_HZ:
            cell = Cell(r, k_o, rate, d, None, felt_trajectory(hz, depth), obj)
            felt_cells[hz].append((oid, cell))
    # simulate in batches (one trajectory per batch: equal lengths), each of one kind of
    # rendering, rate and delay as far as it goes: a batch's servo tick skips what none of its
    # cells needs. The sort is stable, so each rendering's cells keep their hand order
    for tagged_h in hand_cells.values():
        tagged_h.sort(key=lambda item: _batch_class(item[-1]))
    for tagged_f in felt_cells.values():
        tagged_f.sort(key=lambda item: _batch_class(item[-1]))
    follow_cells.sort(key=lambda item: _batch_class(item[-1]))
    stale_cells.sort(key=lambda item: (item[-1].trajectory.name, _batch_class(item[-1])))
    futs: list[tuple[str, Any, list[Any], Any]] = []
    for tr, tagged in hand_cells.items():
        for a in range(0, len(tagged), _BATCH):
            chunk = tagged[a : a + _BATCH]
            cs = [c for *_, c in chunk]
            futs.append(
                ("hand", tr, chunk, pool.submit(_simulate_batch, cs, False, device, options))
            )
    for a in range(0, len(stale_cells), _BATCH):
        chunk_s = stale_cells[a : a + _BATCH]
        for tr in dict.fromkeys(c.trajectory.name for *_, c in chunk_s):
            part = [item for item in chunk_s if item[-1].trajectory.name == tr]
            cs = [c for *_, c in part]
            futs.append(
                ("stale", tr, part, pool.submit(_simulate_batch, cs, False, device, options))
            )
    for hz, tagged_f in felt_cells.items():
        for a in range(0, len(tagged_f), _BATCH):
            chunk_f = tagged_f[a : a + _BATCH]
            cs = [c for _, c in chunk_f]
            futs.append(
                ("felt", hz, chunk_f, pool.submit(_simulate_batch, cs, True, device, options))
            )
    for a in range(0, len(follow_cells), _BATCH):
        chunk_w = follow_cells[a : a + _BATCH]
        cs = [c for _, c in chunk_w]
        futs.append(
            ("follow", None, chunk_w, pool.submit(_simulate_batch, cs, "follow", device, options))
        )
    n_sim = 0
    n_hands = len(hands)
    # (outcome, trajectory, hand) unstable at the stale phase
    stale_unstable: set[tuple[int, int, int]] = set()
    for kind, what, items, fut in futs:
        res = fut.result()
        n_sim += len(res)
        if kind == "felt":
            for (oid, _c), q in zip(items, res, strict=True):
                outcomes[oid].felt[what] = None if q is None else (q[0], q[1])
            continue
        if kind == "follow":
            for (oid, _c), err in zip(items, res, strict=True):
                outcomes[oid].follow_error = err
            continue
        if kind == "stale":
            for (oid, ti, hi, _c), m in zip(items, res, strict=True):
                if not m["stable"]:
                    stale_unstable.add((oid, ti, hi))
            continue
        for (oid, _ti, hi, _c), m in zip(items, res, strict=True):
            o = outcomes[oid]
            if hi < n_box:
                o.stable.append(bool(m["stable"]))
                o.metrics.append(m)
                if what == "impact":
                    o.impact.append(m)
            else:
                o.outside.append(bool(m["stable"]))
    # stable only if stable at both ends of the sampling phase (the flags are in
    # (trajectory, hand) order: the cells of one trajectory are batched together in hand order
    # and trajectories are collected in the grid's order)
    n_out = n_hands - n_box
    for oid, ti, hi in stale_unstable:
        o = outcomes[oid]
        if hi < n_box:
            o.stable[ti * n_box + hi] = False
        else:
            o.outside[ti * n_out + hi - n_box] = False
    # a felt response the probe did not find steady, or still while held, is measured again on
    # the longer probe, every scheme's alike: a rendering that changes once (the product's, when
    # its own-response check identifies the object) is then read after the change; a limit
    # cycle or a growing response is refused again. Only renderings stable with every hand of
    # the box are ranked, so only theirs are measured again
    again: dict[float, list[tuple[int, Cell]]] = defaultdict(list)
    for hz, tagged_f in felt_cells.items():
        for oid, c in tagged_f:
            if outcomes[oid].felt.get(hz) is None and outcomes[oid].box_stable:
                longer = felt_trajectory(hz, c.trajectory.y1_m, longer=True)
                again[hz].append((oid, replace(c, trajectory=longer)))
    futs_again = [
        (hz, chunk_f, pool.submit(_simulate_batch, [c for _, c in chunk_f], True, device, options))
        for hz, tagged_f in again.items()
        for chunk_f in (tagged_f[a : a + _BATCH] for a in range(0, len(tagged_f), _BATCH))
    ]
    n_again = n_again_read = 0
    for hz, items_f, fut in futs_again:
        for (oid, _c), q in zip(items_f, fut.result(), strict=True):
            n_again += 1
            if q is not None:
                n_again_read += 1
                outcomes[oid].felt[hz] = (q[0], q[1])
    return n_sim + n_again, n_again, n_again_read


def _batch_class(cell: Cell) -> tuple[str, bool, bool, bool, bool, float, float]:
    """What of the simulator's servo tick a cell needs (:func:`simulate` skips what none of a
    batch's cells needs): its rendering's kind, passivity layer, two-port form, gain table and
    verified planes; then its simulation rate and delay, which set the ticks a patch arrives at
    (a tick at which none of a batch's cells receives one skips the gains' update)."""
    r = cell.rendering
    return (
        r.kind,
        r.passivity,
        r.two_port,
        r.follows_k_o and bool(r.table),
        bool(r.planes),
        cell.sim_rate_hz,
        cell.delay_ms,
    )


def _chunks(items: Sequence[Cell], size: int) -> Iterable[list[Cell]]:
    for a in range(0, len(items), size):
        yield list(items[a : a + size])


def run(
    *,
    quick: bool = False,
    grid: Grid | None = None,
    schemes: Sequence[str] = SCHEMES,
    device: DeviceModel = DEVICE,
    workers: int | None = None,
    include_3d: bool = True,
    options: RunOptions | None = None,
    seed: int = 0,
    log: Any = None,
    design_cache: dict[tuple[str, GainKey, float], GainDesign] | None = None,
    design_reached: bool = False,
    design_margin: float = DESIGN_MARGIN,
    design_stiffer_by: float = STIFFER_BY,
    plane_check_s: float = 0.0,
    rest_plane: bool = True,
    rest_hold_back_s: float = REST_HOLD_BACK_S,
    both_phases: bool = True,
    two_users: bool = True,
) -> dict[str, Any]:
    """Run the benchmark; returns the ``--json`` document.

    Parameters
    ----------
    quick : bool
        :data:`QUICK_GRID` instead of :data:`FULL_GRID` (ignored when ``grid`` is given).
    grid : Grid, optional
    schemes : sequence of str
        Subset of :data:`haptic_collab.research.fidelity_schemes.SCHEMES`.
    device : DeviceModel
    workers : int, optional
        Worker processes (default: the machine's cores), each with one BLAS thread: this sets
        ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` and ``MKL_NUM_THREADS`` to 1 in the calling
        process's environment where they are not set, before the workers are spawned.
    include_3d : bool
        Also run the 3-D World cells (:mod:`haptic_collab.research.fidelity_3d`).
    options : RunOptions, optional
        Servo jitter and encoder quantisation for every 1-D cell (off by default); its seed
        draws the jitter.
    seed : int
        Recorded in the output, and the jitter's seed when ``options`` has none of its own.
    log : callable, optional
        Progress lines (``print`` to stderr from the CLI).
    design_cache : dict, optional
        Designs already made, keyed ``(mode, GainKey, K_o)``: the design of the gain-table cell
        holding K_o, unscaled (:func:`shared.gains.table.design_cell`); new designs are added to
        it.
    design_reached : bool
        Also design every gain-table cell between the K_o an object is reported at and the K_o
        it reports at the trajectories' held depth (the stiffening object's), as a client has
        them once it has pressed there (slow: about ten more designs per condition). Without
        them the local models render the nearest designed cell below
        (:meth:`shared.gains.table.GainTable.fallback`), as the client does while such a cell is
        being designed.
    design_margin, design_stiffer_by : float
        The local models' design range, as fractions of the K_o reported: their gains are checked
        on objects from ``1 - design_margin`` times the bottom of the cell to ``1 +
        design_stiffer_by`` times its top (:class:`shared.gains.key.GainKey`). The product's
        (0.15, 0.25) by default; narrower, they measure what knowing the object's stiffness that
        well would buy on the spring, and what it costs on the objects the design did not see.
    plane_check_s : float
        Time [s] from the own-response check's first verdict in a cell to that cell's verified
        plane rendering (:attr:`haptic_collab.research.fidelity_schemes.Rendering.plane_delay_s`).
        0 (default): the client has checked the planes around the K_o reported ahead, in the
        background (:func:`shared.gains.verified_plane.ahead_cells`), before the press reaches them;
        :data:`haptic_collab.research.fidelity_schemes.PRODUCT_PLANE_CHECK_S` (2 s): a client
        that checks each plane on arrival (its first seconds after a welcome).
    rest_plane : bool
        The local models render the rest plane where no verified plane does (the client alone
        on the object, :mod:`shared.gains.rest_plane`; default True, as the client); False: the
        designs and verified planes alone (``haptic client --no-rest-plane``).
    rest_hold_back_s : float
        After a verified plane in a contact, the rest plane waits this long [s] without one
        (default the client's, :data:`shared.gains.policy.HOLD_BACK_S`; 0: it renders whenever no
        verified plane does).
    both_phases : bool
        Run every hand cell at both ends of the sampling phase (the simulation taking the force
        of the last or of the first servo tick of its period: :attr:`Cell.stale_sample`); a
        rendering is stable with a hand only if it is at both (the servo's and the
        simulation's clocks are not synchronised). False: the last tick's only, as before
        2026-11-27.
    two_users : bool
        Also run the two-user grid (every condition again with another user pressing and
        letting go: :class:`haptic_collab.research.fidelity_cases.OtherUser`; no rest plane is
        sent), ranked by how the user held still follows the other's press
        (:func:`haptic_collab.research.fidelity_ranking.follow_error`), reported apart.

    Returns
    -------
    dict
        ``schemes``, ``tuning`` (each scheme's sweep, in words), ``grid``, ``device``,
        ``options``, ``conditions`` (one record per object x K_o x rate x delay: each scheme's
        chosen tuning, per-cell stability, felt impedance and metrics, and the ranking),
        ``cells_3d``, ``pairs_3d`` (two users: :func:`haptic_collab.research.fidelity_pairs_3d.run_3d_pairs`),
        ``summary`` (:func:`summarize`; its ``peers_tuned_on_the_design_model``
        is the same summary with each peer keeping, on every object, the tuning it picks on the
        design model in that K_o x rate x delay), ``gains``, ``wall_s``, ``workers``.

    Raises
    ------
    ValueError
        An unknown scheme, or a design range or plane check time out of its domain.
    """
    for s in schemes:
        if s not in SCHEMES:
            raise ValueError(f"unknown scheme {s!r}; expected one of {', '.join(SCHEMES)}")
    if not (math.isfinite(design_margin) and 0.0 <= design_margin < 1.0):
        raise ValueError(f"design_margin must be in [0, 1), got {design_margin!r}")
    if not (math.isfinite(design_stiffer_by) and design_stiffer_by >= 0.0):
        raise ValueError(f"design_stiffer_by must be finite and >= 0, got {design_stiffer_by!r}")
    if not (math.isfinite(rest_hold_back_s) and rest_hold_back_s >= 0.0):
        raise ValueError(f"rest_hold_back_s must be finite and >= 0 s, got {rest_hold_back_s!r}")
    if not (math.isfinite(plane_check_s) and plane_check_s >= 0.0):
        raise ValueError(f"plane_check_s must be finite and >= 0 s, got {plane_check_s!r}")
    key_range = {"margin": design_margin, "stiffer_by": design_stiffer_by}
    g = grid if grid is not None else (QUICK_GRID if quick else FULL_GRID)
    options = options if options is not None else RunOptions()
    if options.seed == 0 and seed:
        options = RunOptions(options.jitter_s, options.quantum_m, seed)
    say = log if log is not None else (lambda _msg: None)
    if include_3d:
        # the 3-D cells' modules (the World, the server's objects) imported before the long 1-D
        # run, not after it: an import that fails ends the run at once, not after half an hour
        from haptic_collab.research.fidelity_3d import run_3d_cells
        from haptic_collab.research.fidelity_pairs_3d import PAIR_SCHEMES, run_3d_pairs
        from haptic_collab.research.fidelity_users_3d import SCHEMES_3D
    t0 = time.perf_counter()
    n_workers = max(1, workers if workers is not None else (os.cpu_count() or 1))
    # one BLAS thread in each worker (they inherit the environment when spawned): with the
    # default one thread per core, two workers' designs oversubscribed a 2-core machine and took
    # nine times as long (the --quick grid's 40 designs: 175 s against 19.5 s, side by side,
    # 2026-11-25); the CLI sets this already, a caller of run() may not have
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    pool: Executor = ProcessPoolExecutor(n_workers, mp_context=mp.get_context("spawn"))
    hands = list(g.hands) + list(g.outside_hands)
    n_box = len(g.hands)
    try:
        # 1. the product's gains for every (mode, rate, delay ticks, K_o): worker processes
        wanted: set[tuple[str, GainKey, float]] = set()
        for scheme in LOCAL_MODELS:
            if scheme not in schemes:
                continue
            mode = "p" if scheme == "local-p" else "pi"
            for rate in g.sim_rate_hz:
                for d in g.delay_ms:
                    for k_o in g.k_o:
                        for name in g.objects:
                            key = _gain_key(
                                mode, rate, d, device, _reported_b_o(name, k_o, rate),
                                **key_range,
                            )  # fmt: skip
                            for k in _k_o_designed(_OBJECTS[name], k_o, design_reached):
                                if design_cache is None or (mode, key, k) not in design_cache:
                                    wanted.add((mode, key, k))
        # both local models' designs of a key and K_o in one job (their compensated candidates
        # are the same: searched once), the longest first, so that no worker is left with one
        # at the end: a design checks N sampling ticks of a loop of about N + delay states
        # (eigenvalues: cubic)
        pairs: dict[tuple[GainKey, float], list[tuple[str, GainKey, float]]] = defaultdict(list)
        for w in sorted(wanted, key=str):
            pairs[(replace(w[1], mode="p"), w[2])].append(w)
        jobs: dict[tuple[GainKey, float], Any] = {
            pk: pool.submit(_design_cells, pk[0], pk[1], tuple(w[1].mode for w in ws))
            for pk, ws in sorted(
                pairs.items(), key=lambda kv: sum(_design_cost(w)[0] for w in kv[1]), reverse=True
            )
        }
        # the verified plane of each cell whose key allows one, each held against its design (by
        # the design's key: a plane's check needs neither the design nor the local model) ...
        planned = {w: w for w in sorted({*(design_cache or {}), *wanted}, key=str)}
        wanted_planes = {w: (w[1], w[2], w) for w in planned if plane_applies(w[1])}
        # ... and the plane of the cell of the stiffness the own-response check identifies on
        # an object whose K_o is reported wrong (spring-0.8, spring-1.2), checked against the
        # design of the cell reported, as the client checks it once identified: the cache the
        # client fills on demand (the simulator renders it the check time after the verdict)
        for w_id, job in _identified_plane_jobs(planned, g.objects, g.k_o).items():
            wanted_planes.setdefault(w_id, job)
        # ... and the plane of each cell an object's K_o reaches that is not designed (the
        # stiffening object's, without design_reached), checked alone, as the client checks it
        # once its own-response check verifies there, before that cell's design is made
        alone = _alone_plane_jobs(planned, g.objects, g.k_o)
        # each plane checked once for both local models, queued behind the designs (the longest
        # first), so that the workers go on to the checks as the designs run out
        to_check = [*((key, k) for key, k, _w in wanted_planes.values()), *alone.values()]
        check_jobs: dict[tuple[GainKey, int], Any] = {}
        for key, k in sorted(to_check, key=lambda c: _design_cost(("p", *c)), reverse=True):
            ck = _plane_check_key(key, k)
            if ck not in check_jobs:
                check_jobs[ck] = pool.submit(_checked_plane_cell, key, k)
        designs: dict[tuple[str, GainKey, float], GainDesign] = dict(design_cache or {})
        for pk, f in jobs.items():
            both = f.result()
            designs.update({w: both[w[1].mode] for w in pairs[pk]})
        checked = {ck: f.result() for ck, f in check_jobs.items()}
        planes = {
            w: _closer(checked[_plane_check_key(key, k)], key, designs[dw])
            for w, (key, k, dw) in wanted_planes.items()
        }
        alone_planes = {w: checked[_plane_check_key(key, k)] for w, (key, k) in alone.items()}
        if design_cache is not None:
            design_cache.update(designs)
        t_design = time.perf_counter() - t0
        n_planes = sum(p is not None for p in planes.values())
        n_alone = sum(p is not None for p in alone_planes.values())
        say(
            f"designed {len(designs)} gain sets and checked {len(checked)} verified planes "
            f"for {len(planes)} cells ({n_planes} render) and {len(alone_planes)} cells a press "
            f"reaches undesigned ({n_alone} render) in {t_design:.1f} s"
        )

        tables: dict[tuple[str, GainKey], tuple[TableCell, ...]] = {}

        # 2. every scheme's renderings (a peer's whole sweep) per (K_o, rate, delay, user count);
        # the local models' per object too, for the B_o the simulation reports with it
        def renderings(
            name: str, s: str, k_o: float, rate: float, d: float, two: bool
        ) -> list[Rendering]:
            if s not in LOCAL_MODELS:
                return peer_renderings(s, k_o=k_o, sim_rate_hz=rate, device=device, alone=not two)
            mode = "p" if s == "local-p" else "pi"
            key = _gain_key(
                mode, rate, d, device, _reported_b_o(name, k_o, rate), **key_range
            )  # fmt: skip
            if (mode, key) not in tables:
                tables[(mode, key)] = _table(designs, mode, key)
            # the planes checked against designs, and those a press into this object checks
            # alone in the cells it reaches that are not designed (these are its own: each is
            # the plane of the K_o reported there, where a spring reported wrong is checked
            # against the design of the cell reported)
            reached = set(_k_o_designed(_OBJECTS[name], k_o, True)[1:])
            by_cell = {c.cell: c for c in _planes(planes, mode, key)}
            own = {w: p for w, p in alone_planes.items() if w[2] in reached}
            by_cell.update({c.cell: c for c in _planes(own, mode, key)})
            return [
                rendering_for(
                    s,
                    sim_rate_hz=rate,
                    device=device,
                    design=designs[(mode, key, k_o)].at(k_o),
                    table=tables[(mode, key)],
                    planes=tuple(by_cell[c] for c in sorted(by_cell)),
                    plane_check_s=plane_check_s,
                    # the server sends the rest plane only to a user alone
                    rest_plane=rest_plane and not two,
                    rest_hold_back_s=rest_hold_back_s,
                )
            ]

        # 3. the grids: the user alone, and (two_users) with another user pressing and letting
        # go. Each peer's tuning is picked as its user would pick it, from what the wire carries:
        # on the spring of the K_o reported (the nominal object), at that rate, delay and user
        # count, every tuning of its sweep is run; the one stable with every hand of the box,
        # then felt closest (choose_variant), is then run on every other object. First the
        # spring's cells (every tuning), then the other objects' (the tuning picked)
        grids = [False, True] if two_users else [False]
        outcomes: list[Outcome] = []
        where: dict[tuple[bool, str, str, float, float, float], list[int]] = {}
        first: list[tuple[int, bool, str, float, float, float]] = []
        for two in grids:
            for s, k_o, rate, d in itertools.product(schemes, g.k_o, g.sim_rate_hz, g.delay_ms):
                ids = []
                for r in renderings("spring", s, k_o, rate, d, two):
                    ids.append(len(outcomes))
                    first.append((len(outcomes), two, "spring", k_o, rate, d))
                    outcomes.append(Outcome(r))
                where[(two, "spring", s, k_o, rate, d)] = ids

        def simulate_all(
            items: list[tuple[int, bool, str, float, float, float]],
        ) -> tuple[int, ...]:
            return _run_outcomes(
                pool, items, outcomes, hands=hands, n_box=n_box, trajectories=g.trajectories,
                device=device, options=options, both_phases=both_phases,
            )  # fmt: skip

        counts = simulate_all(first)
        pick: dict[tuple[bool, str, float, float, float], int] = {}
        for two in grids:
            for s, k_o, rate, d in itertools.product(schemes, g.k_o, g.sim_rate_hz, g.delay_ms):
                ids = where[(two, "spring", s, k_o, rate, d)]
                pick[(two, s, k_o, rate, d)] = choose_variant([outcomes[i] for i in ids])
        second: list[tuple[int, bool, str, float, float, float]] = []
        for two in grids:
            for name in g.objects:
                if name == "spring":
                    continue
                for s, k_o, rate, d in itertools.product(schemes, g.k_o, g.sim_rate_hz, g.delay_ms):
                    rs = renderings(name, s, k_o, rate, d, two)
                    r = rs[0] if s in LOCAL_MODELS else rs[pick[(two, s, k_o, rate, d)]]
                    where[(two, name, s, k_o, rate, d)] = [len(outcomes)]
                    second.append((len(outcomes), two, name, k_o, rate, d))
                    outcomes.append(Outcome(r))
        more = simulate_all(second)
        n_sim, n_again, n_again_read = (x + y for x, y in zip(counts, more, strict=True))
        t_sim = time.perf_counter() - t0 - t_design
        say(
            f"simulated {n_sim} cells in {t_sim:.1f} s ({n_again} felt probes measured again "
            f"on the longer probe, {n_again_read} of them read)"
        )
    finally:
        pool.shutdown()

    # each condition's records: a local model's rendering, a peer's tuning picked on the
    # nominal spring (the spring's own condition: that tuning among its sweep)
    by_grid: dict[bool, list[dict[str, Any]]] = {two: [] for two in grids}
    for two in grids:
        for name in g.objects:
            for k_o in g.k_o:
                for rate in g.sim_rate_hz:
                    for d in g.delay_ms:
                        recs: dict[str, Any] = {}
                        for s in schemes:
                            ids = where[(two, name, s, k_o, rate, d)]
                            i = ids[pick[(two, s, k_o, rate, d)]] if name == "spring" else ids[0]
                            recs[s] = scheme_record(outcomes[i])
                        cond = {
                            "object": name,
                            "k_o_n_per_m": k_o,
                            "sim_rate_hz": rate,
                            "delay_ms": d,
                            "schemes": recs,
                        }
                        rank(cond)
                        by_grid[two].append(cond)
    conditions = by_grid[False]
    conditions_two = by_grid.get(True, [])

    cells3: list[dict[str, Any]] = []
    pairs3: list[dict[str, Any]] = []
    t_3d = 0.0
    if include_3d:
        t3 = time.perf_counter()
        s3 = [s for s in schemes if s in SCHEMES_3D]
        # one pool for the three grids: its workers build each object once (a FEM solid's
        # start-up is 4-5 s) and import once
        pool3 = (
            ProcessPoolExecutor(n_workers, mp_context=mp.get_context("spawn"))
            if n_workers > 1
            else None
        )
        try:
            cells3 = run_3d_cells(
                s3, device=device, workers=n_workers, pool=pool3, rest_plane=rest_plane
            )
            # objects the design was not made on: the stress set's shapes, pressed at their top
            cells3 += run_3d_cells(
                s3,
                device=device,
                workers=n_workers,
                meshes=FIDELITY_MESHES_3D,
                stiffness_scales=(1.0,),
                trajectories=("press",),
                pool=pool3,
                rest_plane=rest_plane,
            )
            # two users on the balloon: B rests on its side while A presses the top
            pairs3 = run_3d_pairs(
                [s for s in schemes if s in PAIR_SCHEMES],
                device=device,
                workers=n_workers,
                pool=pool3,
            )
        finally:
            if pool3 is not None:
                pool3.shutdown()
        t_3d = time.perf_counter() - t3
        say(f"ran {len(cells3)} 3-D cells and {len(pairs3)} two-user cells in {t_3d:.1f} s")

    gains = []
    for (mode, gkey, k_o), cell_design in sorted(
        designs.items(),
        key=lambda kv: (
            kv[0][0],
            kv[0][1].sim_rate_hz,
            kv[0][1].delay_ticks,
            kv[0][1].b_o,
            kv[0][2],
        ),
    ):  # K_o last: the order of the JSON's designs is the same in every run
        gd = cell_design.at(k_o)
        gains.append(
            {
                "local_model": mode,
                "k_o_n_per_m": k_o,
                "sim_rate_hz": gkey.sim_rate_hz,
                "delay_ticks": gkey.delay_ticks,
                "b_o_n_per_m": gkey.b_o,
                "k_h": gd.k_h,
                "i_gain": gd.i_gain,
                "b_h": gd.b_h,
                "own_gain": gd.own_gain,
                "proxy_hold": gd.proxy_hold,
                "rendered_as": gd.mode,
                "verified_plane": _plane_json(planes.get((mode, gkey, k_o)), k_o),
            }
        )
    summary = summarize(conditions, schemes)
    if conditions_two:
        summary["two_users"] = summarize(conditions_two, schemes)
    if cells3:
        summary["stable_fraction_3d"] = {
            s: sum(c["stable"] for c in cells3 if c["scheme"] == s)
            / max(1, sum(c["scheme"] == s for c in cells3))
            for s in dict.fromkeys(c["scheme"] for c in cells3)
        }
    if pairs3:
        summary["two_users_3d"] = {
            s: {
                "settled_fraction": sum(p["settled"] for p in ps) / len(ps),
                "b_feels_a_fraction": sum(p["b_feels_a"] for p in ps) / len(ps),
                "median_b_force_rise_n": statistics.median(p["b_force_rise_n"] for p in ps),
                "median_object_force_rise_n": statistics.median(
                    p["object_force_rise_n"] for p in ps
                ),
            }
            for s in dict.fromkeys(p["scheme"] for p in pairs3)
            for ps in [[p for p in pairs3 if p["scheme"] == s]]
        }
    return {
        "schemes": list(schemes),
        "tuning": {s: scheme_tuning(s, device) for s in schemes},
        "grid": {**g.as_dict(), "quick": quick and grid is None},
        "objects": {
            name: {
                k: getattr(_OBJECTS[name], k)
                for k in ObjectModel.__dataclass_fields__  # noqa: SIM118
            }
            for name in g.objects
        },
        "felt_hz": list(FELT_HZ),
        "felt_probe": {
            "sine_start_s": FELT_SINE_START_S,
            "settle_s": FELT_SETTLE_S,
            "retry_extra_s": FELT_RETRY_EXTRA_S,
            "measured_again": n_again,
            "read_again": n_again_read,
        },
        "device": {
            "name": device.name,
            "max_force_n": device.max_force_n,
            "max_stiffness_n_per_m": device.max_stiffness_n_per_m,
            "max_damping_n_s_per_m": device.max_damping_n_s_per_m,
        },
        "options": {
            "jitter_s": options.jitter_s,
            "quantum_m": options.quantum_m,
            "seed": options.seed,
            "design_reached": design_reached,
            "design_margin": design_margin,
            "design_stiffer_by": design_stiffer_by,
            "plane_check_s": plane_check_s,
            "rest_plane": rest_plane,
            "rest_hold_back_s": rest_hold_back_s,
            "both_sampling_phases": both_phases,
            "two_users": two_users,
        },
        "peer_tuning": (
            "picked on the spring of the K_o reported, per K_o, rate, delay and user count "
            "(stable with every hand of the box, then the least error), then judged on every "
            "object"
        ),
        "stale_sample": "the state N // 2 servo ticks old (the client's state every half period)",
        "two_users": (
            None
            if not conditions_two
            else {
                "other_user_hands": OTHER_USER.__repr__(),
                "other_user_follow": OTHER_USER_FOLLOW.__repr__(),
                "trajectories": list(g.trajectories),
                "error": "follow error: |ln| of the felt rise and fall over the object's own",
            }
        ),
        "conditions": conditions,
        "conditions_two_users": conditions_two,
        "cells_3d": cells3,
        "pairs_3d": pairs3,
        "summary": summary,
        "gains": gains,
        "seed": seed,
        "wall_s": {
            "design": t_design,
            "simulate_1d": t_sim,
            "world_3d": t_3d,
            "total": time.perf_counter() - t0,
        },
        "workers": n_workers,
    }


# ------------------------------------------------------------------------------------ plots
def plot(result: dict[str, Any], out_dir: Path) -> list[Path]:
    """Write ``fidelity-stability.png`` (each scheme's share of object models on which it is
    stable with every hand of the box, over K_o x delay, one panel per simulation rate) and
    ``fidelity-transparency.png`` (median felt |q| over frequency per scheme, on the design
    model and on the objects it did not see) into ``out_dir``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    out_dir.mkdir(parents=True, exist_ok=True)
    conds = result["conditions"]
    schemes = result["schemes"]
    grid = result["grid"]
    k_os, rates, delays = grid["k_o_n_per_m"], grid["sim_rate_hz"], grid["delay_ms"]
    share: dict[tuple[str, float, float, float], list[bool]] = defaultdict(list)
    for c in conds:
        for s, r in c["schemes"].items():
            share[(s, c["k_o_n_per_m"], c["sim_rate_hz"], c["delay_ms"])].append(r["box_stable"])
    fig = Figure(figsize=(2.4 * len(rates) + 1.2, 1.7 * len(schemes) + 0.6))
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(schemes), len(rates), squeeze=False)
    im = None
    for i, s in enumerate(schemes):
        for j, rate in enumerate(rates):
            ax = axes[i][j]
            data = [
                [
                    (lambda v: sum(v) / len(v) if v else math.nan)(share.get((s, k, rate, d), []))
                    for k in k_os
                ]
                for d in delays
            ]
            im = ax.imshow(data, origin="lower", vmin=0.0, vmax=1.0, cmap="RdYlGn", aspect="auto")
            ax.set_xticks(range(len(k_os)), [f"{k:g}" for k in k_os], fontsize=7)
            ax.set_yticks(range(len(delays)), [f"{d:g}" for d in delays], fontsize=7)
            if i == 0:
                ax.set_title(f"{rate:g} Hz", fontsize=9)
            if j == 0:
                ax.set_ylabel(f"{s}\ndelay [ms]", fontsize=8)
            if i == len(schemes) - 1:
                ax.set_xlabel("K_o [N/m]", fontsize=8)
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.6, label="share of object models stable with every hand")
    fig.suptitle("Stable with every hand of the box (1-D, every trajectory)", fontsize=10)
    p1 = out_dir / "fidelity-stability.png"
    fig.savefig(p1, dpi=90)

    fig2 = Figure(figsize=(9.0, 3.6))
    FigureCanvasAgg(fig2)
    axs = fig2.subplots(1, 2, sharey=True)
    hz = result["felt_hz"]
    for ax, (title, pick) in zip(
        axs,
        (
            ("design model (spring)", lambda c: c["object"] == "spring"),
            ("objects the design did not see", lambda c: c["object"] != "spring"),
        ),
        strict=True,
    ):
        for s in schemes:
            meds = []
            for f in hz:
                v = [
                    c["schemes"][s]["felt"][f"{f:g}"][0]
                    for c in conds
                    if pick(c)
                    and c["schemes"][s]["box_stable"]
                    and c["schemes"][s]["felt"].get(f"{f:g}") is not None
                ]
                meds.append(statistics.median(v) if v else math.nan)
            ax.plot(hz, meds, marker="o", ms=3, label=s)
        ax.axhspan(1.0 / (1.0 + STIFFNESS_JND), 1.0 + STIFFNESS_JND, color="0.85", zorder=0)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(0.1, 10.0)
        ax.set_xlabel("frequency [Hz]")
        ax.set_title(title, fontsize=9)
    axs[0].set_ylabel("median felt |dF/dx| / object's own\n(box-stable conditions)")
    axs[1].legend(fontsize=7, ncol=2)
    fig2.tight_layout()
    p2 = out_dir / "fidelity-transparency.png"
    fig2.savefig(p2, dpi=90)
    return [p1, p2]
