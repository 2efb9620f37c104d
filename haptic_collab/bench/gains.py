"""``haptic bench gains``: what a gain update costs the client's network loop, and what a design costs.

A patch's gains are a :class:`shared.gains.table.GainTable` lookup inside
:meth:`client.session.ClientSession.receive` (on the asyncio loop); a missing cell is designed in a
worker process. This bench measures, in one run on this machine:

- ``patch_ms``: the whole ``receive`` of a ``patch`` frame with its cell designed (JSON parsing,
  primitive, lookup), p50 / p99 over 2000 patches whose K_o wanders over a few cells;
- ``lookup_us``: the table lookup alone, p50 / p99;
- ``design_ms``: one cell's design (what the worker process spends: :func:`design_cell` with the
  session's key, own-force compensation and the cell's K_o range), p50 / p99 for P and PI over
  K_o from 50 to 5000 N/m at 20 Hz without delay;
- ``plane_check_ms``: one verified plane's check (what the worker spends on a plane it checks
  ahead: :func:`shared.gains.verified_plane.checked_plane`), p50 / p99 over the cells of
  :data:`PLANE_CHECK_K_OS` at 20 Hz with 0, 2 and 4 ticks of delay, the capped planes of the
  cells above the device's stiffness included.

Wall-clock medians: the machine is shared, compare ratios measured side by side.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from haptic_collab.client.session import ClientSession
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.table import GainTable, design_cell
from haptic_collab.shared.gains.verified_plane import checked_plane
from haptic_collab.shared.protocol import DeviceInfo, ObjectInfo, Patch, PlaneModel, Welcome, encode

#: The K_o [N/m] whose cells' verified planes ``plane_check_ms`` times: soft, at the bench
#: device's stiffness (1000 N/m) and the two capped cells above it.
PLANE_CHECK_K_OS: tuple[float, ...] = (100.0, 300.0, 1000.0, 1100.0, 1200.0)

#: The object the bench's welcome describes: an octahedron of radius 0.1 m about the origin [m].
_OBJECT = ObjectInfo(
    n_vertices=6,
    n_faces=8,
    center_m=(0, 0, 0),
    radius_m=0.1,
    bounds_min_m=(-0.1, -0.1, -0.1),
    bounds_max_m=(0.1, 0.1, 0.1),
    top_m=(0, 0, 0.1),
    top_normal=(0, 0, 1),
    side_m=(0.1, 0, 0),
    side_normal=(1, 0, 0),
)


def _top_patch(tick: int, k_o: float) -> str:
    """A ``patch`` frame 2 mm into the top plane z = 0.1 m, in contact, K_o = K_o,eff = ``k_o``."""
    top = PlaneModel(point=(0, 0, 0.1), normal=(0, 0, 1))
    return encode(
        Patch(tick=tick, primitive=top, proxy_m=(0, 0, 0.1), normal=(0, 0, 1), penetration_m=0.002,
              in_contact=True, k_o=k_o, k_o_eff=k_o, b_o=0.0)
    )  # fmt: skip


def _session() -> ClientSession:
    """A PI session (B_h up to 10 N·s/m) that received a 20 Hz welcome at 0 s."""
    s = ClientSession(
        "bench", device=DeviceInfo(max_stiffness_n_per_m=1000.0), mode="pi", b_h_max=10.0
    )
    welcome = Welcome(user_id="u", name="bench", role="user", sim_rate_hz=20.0, object=_OBJECT)
    s.receive(encode(welcome), 0.0)
    return s


def _pcts(values: list[float]) -> dict[str, float]:
    a = np.asarray(values)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99))}


def plane_check_ms(
    table: GainTable, key: GainKey, k_os: tuple[float, ...] = PLANE_CHECK_K_OS
) -> list[float]:
    """Wall time [ms] of :func:`shared.gains.verified_plane.checked_plane` for the cell of each of
    ``k_os`` under ``key`` with 0, 2 and 4 ticks of delay, in that order (K_o major)."""
    times = []
    for k_o in k_os:
        for ticks in (0, 2, 4):
            t0 = time.perf_counter()
            checked_plane(
                replace(key, delay_ticks=ticks), table.cell(k_o), table.grid_ratio, table.hand_box
            )
            times.append((time.perf_counter() - t0) * 1e3)
    return times


def run(n_patches: int = 2000, seed: int = 0) -> dict[str, Any]:
    """Run the bench; return the JSON object (module docstring)."""
    rng = np.random.default_rng(seed)
    s = _session()
    k_os = 300.0 * np.exp(rng.uniform(-0.2, 0.2, n_patches))
    # design the cells the run visits (off the measured path, as the worker process would)
    key = s.gain_key(0.0, 0)
    for k in sorted({s.gain_table.cell(float(k)) for k in k_os}):
        s.gain_table.design(key, s.gain_table.grid_point(k) * 1.0001)
    frames = [_top_patch(i + 1, float(k)) for i, k in enumerate(k_os)]
    patch_ms = []
    for i, fr in enumerate(frames):
        t0 = time.perf_counter()
        up = s.receive(fr, 1.0 + 0.05 * i)
        patch_ms.append((time.perf_counter() - t0) * 1e3)
        assert up is not None and up.choice is not None and not up.choice.fallback
    lookup_us = []
    for k in k_os[:500]:
        t0 = time.perf_counter()
        s.gain_table.lookup(key, float(k))
        lookup_us.append((time.perf_counter() - t0) * 1e6)
    # what the worker runs for a missing cell: design_cell with the session's key (own-force
    # compensation, the cell's K_o range), for a P and a PI local model
    table = s.gain_table
    design: dict[str, dict[str, float]] = {}
    for mode in ("p", "pi"):
        key_m = replace(key, mode=mode)
        times = []
        for k_o in (50.0, 150.0, 300.0, 1000.0, 5000.0):
            t0 = time.perf_counter()
            design_cell(key_m, table.cell(k_o), table.grid_ratio, table.hand_box)
            times.append((time.perf_counter() - t0) * 1e3)
        design[mode] = _pcts(times)
    return {
        "patches": n_patches,
        "patch_ms": _pcts(patch_ms),
        "lookup_us": _pcts(lookup_us),
        "design_ms": design,
        "plane_check_ms": _pcts(plane_check_ms(table, key)),
        "cells_designed": len(s.gain_table),
    }
