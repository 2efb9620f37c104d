"""Servo telemetry: a preallocated ring buffer the 1 kHz tick writes with plain float stores.

One row per servo tick, columns :data:`COLUMNS` (units in the names). The tick calls
:meth:`TelemetryRecorder.append` with exactly ``len(COLUMNS)`` floats; it packs them into a
preallocated ``array('d')`` (the buffer never grows; no lock, no logging; CPython still makes the
call's small objects, so "allocation-free" is not a claim made here) and overwrites the oldest row
when the buffer is full. Everything else (:meth:`rows`, :meth:`column`, :meth:`write_csv`) runs outside
the tick and copies; call it after the servo loop stopped for a consistent snapshot (while it runs
the newest row may be half written).

:class:`CsvRecording` streams the rows to a CSV file while the servo loop runs (``haptic client
--record``): a writer thread copies the rows appended since its last pass every
``flush_interval_s`` and appends them to the file, so memory stays bounded by the ring however long
the client runs, and :meth:`CsvRecording.close` writes the rest (the client calls it on exit,
SIGINT and SIGTERM included). :func:`load_recording` reads such a file back and
:func:`plot_recording` draws it (matplotlib, imported only there).
"""

from __future__ import annotations

import array
import logging
import os
import struct
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

log = logging.getLogger("haptic.client")

#: Column names of a telemetry row, with units: [m], [N], [N/m], [N/(m*s)], [s], [m/N]; flags are 0/1.
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
    "own_offset_m",
    "own_gain_m_per_n",
)
_INT_COLUMNS = frozenset({"tick", "in_contact", "ramping", "fault", "force_limited"})
_COMPUTE_COL = COLUMNS.index("compute_s")


class TelemetryRecorder:
    """Ring buffer of servo telemetry rows (module docstring).

    Parameters
    ----------
    capacity : int
        Rows kept, >= 1 (default 120000: two minutes at 1 kHz, about 23 MB).
    buffer, counter : memoryview, optional
        Shared memory to keep the rows in (:meth:`nbytes` bytes) and the count of rows ever
        appended (an int64 view): the servo process writes a ring that the client's link process
        reads (:mod:`client.servo_process`). Default: private memory.

    Raises
    ------
    ValueError
        ``capacity < 1``; a buffer too small, or one without its counter.
    """

    columns = COLUMNS

    def __init__(
        self,
        capacity: int = 120_000,
        *,
        buffer: memoryview | None = None,
        counter: memoryview | None = None,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1 row, got {capacity!r}")
        self.capacity = int(capacity)
        self._ncols = len(COLUMNS)
        self._row = struct.Struct(f"{self._ncols}d")
        size = self.nbytes(self.capacity)
        if (buffer is None) != (counter is None):
            raise ValueError("buffer and counter go together")
        if buffer is None or counter is None:
            self._buf: Any = array.array("d", bytes(size))
            self._meta: Any = array.array("q", [0])
        else:
            if buffer.nbytes < size or counter.format != "q" or len(counter) < 1:
                raise ValueError(
                    f"a shared ring of {self.capacity} rows needs {size} bytes and an int64 counter"
                )
            self._buf = buffer.cast("B")[:size].cast("d")
            self._meta = counter

    @property
    def _count(self) -> int:
        return int(self._meta[0])

    @_count.setter
    def _count(self, n: int) -> None:
        self._meta[0] = n

    @classmethod
    def nbytes(cls, capacity: int) -> int:
        """Bytes of the ring of ``capacity`` rows (the size of a shared ``buffer``)."""
        return 8 * len(COLUMNS) * int(capacity)

    def __len__(self) -> int:
        """Rows held now (at most ``capacity``)."""
        return min(self._count, self.capacity)

    @property
    def total(self) -> int:
        """Rows ever appended (including the overwritten ones)."""
        return self._count

    def append(self, *values: float) -> None:
        """Store one row of ``len(COLUMNS)`` floats (called by the servo tick; the ring never grows).

        Raises
        ------
        struct.error
            Wrong number of values (a programming error, not a runtime condition).
        """
        meta = self._meta
        n = meta[0]
        self._row.pack_into(self._buf, 8 * self._ncols * (n % self.capacity), *values)
        meta[0] = n + 1

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

    def rows_from(
        self, start: int, stop: int | None = None, *, settled: bool = False
    ) -> tuple[int, np.ndarray]:
        """Copy of the rows with absolute index in ``[start, stop)`` that are still held.

        Absolute indices count every row ever appended (0 for the first, :attr:`total` - 1 for the
        newest). Safe while the servo loop appends: rows the ring may have overwritten during the
        copy are left out (with the ring full, the oldest held row shares its slot with the row
        being appended, so it is left out too unless ``settled``).

        Parameters
        ----------
        start : int
            First absolute index wanted, >= 0.
        stop : int, optional
            One past the last index wanted (default :attr:`total`).
        settled : bool
            Nothing appends any more (the servo loop stopped): every held row is whole.

        Returns
        -------
        first : int
            Absolute index of the first row returned (> ``start`` when older rows were
            overwritten before they were copied: ``first - start`` rows are lost).
        rows : (m, len(COLUMNS)) float64
            The rows, oldest first (m may be 0).
        """
        cap, ncols = self.capacity, self._ncols
        n = self._count if stop is None else min(int(stop), self._count)
        lo = max(int(start), n - cap, 0)
        if lo >= n:
            return max(lo, int(start)), np.empty((0, ncols))
        data = np.frombuffer(self._buf, dtype=np.float64).reshape(cap, ncols)
        i0, i1 = lo % cap, n % cap
        if i0 < i1:
            out = data[i0:i1].copy()
        else:
            out = np.concatenate((data[i0:], data[:i1]))
        # the row at absolute index `after` (slot after % cap) may have been written meanwhile:
        # rows j <= after - cap share a slot with a newer row; drop them
        after = self._count
        safe = after - cap + (0 if settled else 1)
        if safe > lo:
            cut = min(safe - lo, out.shape[0])
            out = out[cut:]
            lo += cut
        return lo, out

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
        with Path(path).open("w", encoding="utf-8", newline="") as fh:
            fh.write(CSV_HEADER)
            fh.write(format_rows(data))
        return int(data.shape[0])


#: First line of a telemetry CSV: the column names, units in the names.
CSV_HEADER = ",".join(COLUMNS) + "\n"
_ROW_FORMAT = ",".join("%d" if c in _INT_COLUMNS else "%.9g" for c in COLUMNS) + "\n"


def format_rows(rows: np.ndarray) -> str:
    """CSV lines of telemetry rows ((m, len(COLUMNS)) float64): flags and ticks as integers."""
    fmt = _ROW_FORMAT
    return "".join(fmt % tuple(r) for r in rows.tolist())


class CsvRecording:
    """Stream a :class:`TelemetryRecorder` to a CSV file while the servo loop runs.

    A daemon thread wakes every ``flush_interval_s``, copies the rows appended since its last
    pass (all but the newest, whose ``compute_s`` the servo thread may still set), appends them to
    the file and flushes it. Memory is the recorder's ring, whatever the run length; the ring must
    hold more than ``flush_interval_s`` of rows (it holds two minutes by default), otherwise the
    rows overwritten before they were copied are counted in :attr:`rows_dropped`. The file has the
    header of :meth:`TelemetryRecorder.write_csv` and the same format.

    Parameters
    ----------
    recorder : TelemetryRecorder
        The servo loop's telemetry.
    path : str or Path
        The CSV file (created with its parent folders, truncated).
    flush_interval_s : float
        Seconds between two writes, > 0 (default 0.2: a crash loses at most that much).

    Raises
    ------
    ValueError
        ``flush_interval_s`` not > 0.
    OSError
        The file cannot be created (raised by :meth:`start`).
    """

    def __init__(
        self, recorder: TelemetryRecorder, path: str | Path, *, flush_interval_s: float = 0.2
    ) -> None:
        if not (flush_interval_s > 0.0):
            raise ValueError(f"flush_interval_s must be > 0 s, got {flush_interval_s!r}")
        self.recorder = recorder
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.rows_written = 0
        self.rows_dropped = 0
        self.error: str | None = None
        self._next = recorder.total
        self._fh: IO[str] | None = None
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Create the file, write the header and start the writer thread.

        Raises
        ------
        OSError
            The file cannot be created.
        """
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = self.path.open("w", encoding="utf-8", newline="")
        self._fh.write(CSV_HEADER)
        self._fh.flush()
        self._thread = threading.Thread(target=self._main, name="record-writer", daemon=True)
        self._thread.start()

    def _main(self) -> None:
        while not self._halt.wait(self.flush_interval_s):
            self.drain(final=False)

    def drain(self, *, final: bool = False) -> int:
        """Append the rows recorded since the last drain to the file and flush it.

        Parameters
        ----------
        final : bool
            Also write the newest row (only once the servo loop has stopped).

        Returns
        -------
        int
            Rows written by this call (0 after a write error, which is kept in :attr:`error`).
        """
        with self._lock:
            fh = self._fh
            if fh is None:
                return 0
            total = self.recorder.total
            first, rows = self.recorder.rows_from(
                self._next, total if final else total - 1, settled=final
            )
            if first > self._next:
                self.rows_dropped += first - self._next
            if rows.shape[0] == 0:
                self._next = max(self._next, first)
                return 0
            self._next = first + rows.shape[0]
            try:
                fh.write(format_rows(rows))
                fh.flush()
            except (OSError, ValueError) as exc:
                if self.error is None:
                    self.error = str(exc)
                    log.error("recording to %s failed: %s", self.path, exc)
                return 0
            self.rows_written += rows.shape[0]
            return int(rows.shape[0])

    def close(self) -> int:
        """Stop the writer thread, write every remaining row, flush, sync and close the file.

        Call it after the servo loop stopped (or the newest row may be half written); safe to
        call twice.

        Returns
        -------
        int
            Rows in the file.
        """
        self._halt.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.drain(final=True)
        with self._lock:
            fh, self._fh = self._fh, None
            if fh is not None:
                try:
                    fh.flush()
                    os.fsync(fh.fileno())
                except OSError as exc:
                    if self.error is None:
                        self.error = str(exc)
                fh.close()
        return self.rows_written


def load_recording(path: str | Path) -> dict[str, np.ndarray]:
    """Columns of a telemetry CSV (``haptic client --record``) by name, each (m,) float64.

    Raises
    ------
    ValueError
        Not a telemetry CSV (no ``t_s`` or probe columns) or unreadable numbers.
    OSError
        The file cannot be read.
    """
    p = Path(path)
    with p.open(encoding="utf-8") as fh:
        header = [h.strip() for h in fh.readline().strip().split(",")]
    need = ("t_s", "probe_x_m", "probe_y_m", "probe_z_m")
    missing = [c for c in need if c not in header]
    if missing:
        raise ValueError(
            f"{p} is not a --record file: its header lacks {', '.join(missing)} "
            f"(expected the columns {', '.join(COLUMNS[:5])}, ...)"
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # a file with a header only: no rows
        data = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
    if data.shape[0] and data.shape[1] != len(header):
        raise ValueError(f"{p}: {data.shape[1]} values per row for {len(header)} columns")
    if data.shape[0] == 0:
        data = np.empty((0, len(header)))
    return {h: data[:, i] for i, h in enumerate(header)}


def plot_probe_proxy(ax: Any, cols: dict[str, np.ndarray], t_shift_s: float = 0.0) -> None:
    """Draw probe and proxy along the contact normal [mm] against time [s] on a matplotlib axis.

    The normal is the mean direction of the force when it is above 0.05 N (else +z); positions are
    relative to the surface at the first contact (0: where the surface was when touched).

    Parameters
    ----------
    ax : matplotlib Axes
        Where to draw.
    cols : dict of (m,) float64
        Columns of a recording (:func:`load_recording`).
    t_shift_s : float
        Added to the recording's times [s] (to put several recordings on one clock).
    """
    t = cols["t_s"] + t_shift_s
    probe = np.stack([cols["probe_x_m"], cols["probe_y_m"], cols["probe_z_m"]], axis=1)
    proxy = np.stack([cols["proxy_x_m"], cols["proxy_y_m"], cols["proxy_z_m"]], axis=1)
    fvec = np.stack([cols["force_x_n"], cols["force_y_n"], cols["force_z_n"]], axis=1)
    fmag = np.linalg.norm(fvec, axis=1)
    strong = fmag > 0.05
    normal = (
        np.nanmean(fvec[strong] / fmag[strong, None], axis=0)
        if strong.any()
        else np.array([0.0, 0.0, 1.0])
    )
    normal = normal / np.linalg.norm(normal)
    ok = np.isfinite(proxy).all(axis=1) & (cols["k_h_n_per_m"] > 0)  # a patch is in use
    touching = ok & (cols["in_contact"] > 0)
    if touching.any():
        ref = proxy[touching][0]
    elif ok.any():
        ref = proxy[ok][0]
    else:
        ref = probe[0] if probe.shape[0] else np.zeros(3)
    ax.plot(t, (probe - ref) @ normal * 1000.0, label="probe $x_h$ (device)", color="tab:blue")
    ax.plot(
        t[ok], (proxy[ok] - ref) @ normal * 1000.0, label="proxy $x_o$ (surface)", color="tab:red"
    )
    ax.set_ylabel("outward position [mm]\n(0: surface at first contact)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")


def plot_recording(paths: Sequence[str | Path], out: str | Path) -> Path:
    """PNG of one or more recordings: each one's probe and proxy, then every force [N], vs time.

    The layout of ``haptic demo --plot``: one panel per recording with probe and proxy along the
    contact normal (:func:`plot_probe_proxy`), then one panel with the force on each user. Each
    recording keeps its own clock (t = 0 when its client started). matplotlib is imported here,
    only (the ``plots`` extra).

    Parameters
    ----------
    paths : sequence of str or Path
        ``--record`` CSV files, at least one.
    out : str or Path
        The PNG to write (parent folders are created).

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    ValueError
        No file, or a file that is not a recording.
    OSError
        A file cannot be read or the PNG cannot be written.
    ImportError
        matplotlib is not installed.
    """
    if not paths:
        raise ValueError("give at least one recording")
    recs = [(Path(p), load_recording(p)) for p in paths]
    for p, cols in recs:
        if cols["t_s"].size == 0:
            raise ValueError(f"{p} holds no samples")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(recs)
    fig, axes = plt.subplots(n + 1, 1, figsize=(11, 3 * (n + 1)), sharex=True, squeeze=False)
    ax_f = axes[n, 0]
    for i, (p, cols) in enumerate(recs):
        plot_probe_proxy(axes[i, 0], cols)
        axes[i, 0].set_title(p.name)
        ax_f.plot(cols["t_s"], cols["force_n"], label=p.stem)
    ax_f.set_ylabel("force on the user [N]")
    ax_f.set_xlabel("time [s] (each recording's own clock)")
    ax_f.grid(alpha=0.3)
    ax_f.legend(loc="upper left")
    fig.tight_layout()
    out_path = Path(out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=120)
    plt.close(fig)
    return out_path
