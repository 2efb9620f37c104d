"""Servo telemetry: a preallocated ring buffer the 1 kHz tick writes with plain float stores.

One row per servo tick, columns :data:`COLUMNS` (units in the names). The tick calls
:meth:`TelemetryRecorder.append` with exactly ``len(COLUMNS)`` floats; it packs them into a
preallocated ``array('d')`` (no allocation, no lock, no logging) and overwrites the oldest row when
the buffer is full. Everything else (:meth:`rows`, :meth:`column`, :meth:`write_csv`) runs outside
the tick and copies; call it after the servo loop stopped for a consistent snapshot (while it runs
the newest row may be half written).
"""

from __future__ import annotations

import array
import struct
from pathlib import Path

import numpy as np

#: Column names of a telemetry row, with units: [m], [N], [N/m], [N/(m*s)], [s]; flags are 0/1.
COLUMNS: tuple[str, ...] = (
    "tick",
    "t_s",
    "probe_x_m",
    "probe_y_m",
    "probe_z_m",
    "proxy_x_m",
    "proxy_y_m",
    "proxy_z_m",
    "penetration_m",
    "force_x_n",
    "force_y_n",
    "force_z_n",
    "force_n",
    "k_h_n_per_m",
    "i_gain_n_per_m_s",
    "integral_n",
    "theta_m",
    "period_s",
    "compute_s",
    "force_scale",
    "in_contact",
    "ramping",
    "fault",
    "force_limited",
    "b_h_n_s_per_m",
    "pc_observed_j",
    "pc_dissipated_j",
)
_INT_COLUMNS = frozenset({"tick", "in_contact", "ramping", "fault", "force_limited"})
_COMPUTE_COL = COLUMNS.index("compute_s")


class TelemetryRecorder:
    """Ring buffer of servo telemetry rows (module docstring).

    Parameters
    ----------
    capacity : int
        Rows kept, >= 1 (default 120000: two minutes at 1 kHz, about 23 MB).

    Raises
    ------
    ValueError
        ``capacity < 1``.
    """

    columns = COLUMNS

    def __init__(self, capacity: int = 120_000) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1 row, got {capacity!r}")
        self.capacity = int(capacity)
        self._ncols = len(COLUMNS)
        self._row = struct.Struct(f"{self._ncols}d")
        self._buf = array.array("d", bytes(8 * self._ncols * self.capacity))
        self._count = 0

    def __len__(self) -> int:
        """Rows held now (at most ``capacity``)."""
        return min(self._count, self.capacity)

    @property
    def total(self) -> int:
        """Rows ever appended (including the overwritten ones)."""
        return self._count

    def append(self, *values: float) -> None:
        """Store one row of ``len(COLUMNS)`` floats (called by the servo tick; allocation-free).

        Raises
        ------
        struct.error
            Wrong number of values (a programming error, not a runtime condition).
        """
        n = self._count
        self._row.pack_into(self._buf, 8 * self._ncols * (n % self.capacity), *values)
        self._count = n + 1

    def set_compute_s(self, compute_s: float) -> None:
        """Overwrite ``compute_s`` [s] of the newest row (measured after the tick returned)."""
        n = self._count
        if n:
            self._buf[self._ncols * ((n - 1) % self.capacity) + _COMPUTE_COL] = compute_s

    def clear(self) -> None:
        """Forget every row."""
        self._count = 0

    def rows(self) -> np.ndarray:
        """Copy of the held rows, oldest first: (n, len(COLUMNS)) float64."""
        n, cap = self._count, self.capacity
        data = np.frombuffer(self._buf, dtype=np.float64).reshape(cap, self._ncols)
        if n <= cap:
            return data[:n].copy()
        start = n % cap
        return np.concatenate((data[start:], data[:start]))

    def column(self, name: str) -> np.ndarray:
        """Copy of one column, oldest first: (n,) float64.

        Raises
        ------
        ValueError
            Unknown column name.
        """
        if name not in COLUMNS:
            raise ValueError(f"unknown telemetry column {name!r}; columns: {', '.join(COLUMNS)}")
        return self.rows()[:, COLUMNS.index(name)]

    def write_csv(self, path: str | Path) -> int:
        """Write the held rows, oldest first, as CSV with a header naming units.

        Returns
        -------
        int
            Rows written.

        Raises
        ------
        OSError
            The file cannot be written.
        """
        data = self.rows()
        fmt = ["%d" if c in _INT_COLUMNS else "%.9g" for c in COLUMNS]
        with Path(path).open("w", encoding="utf-8", newline="") as fh:
            np.savetxt(fh, data, fmt=fmt, delimiter=",", header=",".join(COLUMNS), comments="")
        return int(data.shape[0])
