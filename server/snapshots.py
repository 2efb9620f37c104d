"""Room snapshots: a draining server saves each room's object state; a room made again resumes it.

On SIGTERM (:meth:`server.app.ServerApp.drain`) every room's object state is written to the
snapshot directory (``haptic server --snapshot-dir DIR``), one file per room, ``DIR/NAME.npz``
(NAME is the room's name, ``default`` for ``/ws``). When a room of that name is made again by a
server given the same directory (at the start, or on demand), it starts from the file's state
instead of rest, and logs that it did.

The file is numpy's ``.npz`` (a zip of ``.npy`` arrays; no pickle: it is read with
``np.load(allow_pickle=False)``), written atomically: to a temporary file in the same directory,
flushed to disk, then renamed over ``NAME.npz`` (``os.replace``), so a reader sees the old file
or the new one, never half of one. It holds:

- ``format_version`` (:data:`FORMAT_VERSION`), ``room`` (the room's name), ``tick`` (the last
  simulation tick run), ``written_unix_s`` (when, [s] since the epoch);
- the object's description (:func:`describe`): ``object_kind`` (``balloon`` or ``fem``),
  ``n_vertices``, ``n_faces``, ``mesh_sha256`` (SHA-256 of the rest vertices, float64, and
  faces, int32), ``volume_sha256`` (the FEM solid's nodes and tetrahedra; '' for the balloon)
  and ``params_sha256`` (its physical parameters, the patch cache's size left out): a snapshot
  of another object, mesh, material or rate is refused;
- ``vertices`` (n, 3) [m], the surface shown when it was written;
- ``state_KEY`` arrays: the object's dynamic state (:func:`object_state`): the balloon's normal
  displacement ``w`` (n,) [m]; the FEM solid's ``u`` (3n,) [m], ``w`` (3n,) [rad] and ``q``
  (n_modes, 2) (:meth:`server.objects.fem.FemSolid.state`).

A snapshot is consumed when a room is made from it: ``NAME.npz`` is first renamed to
``NAME.npz.loading`` (an atomic claim: two servers sharing the directory cannot both load it),
then to ``NAME.npz.loaded`` once the state is in the room, or to ``NAME.npz.refused`` when it
was refused (another object, a corrupt file, another format version; the log says why, and the
room starts from rest). Neither is ever read again, so an old state is not resurrected by a
later restart; renaming one back to ``NAME.npz`` offers it again. The next drain writes a new
``NAME.npz``.

Restoring never raises: whatever goes wrong is logged and the room starts from rest. What the
state means is physics: the static balloon (damping 0, the default) has no memory, its surface
is the response to the pushes of the tick, so its restored surface lasts until the first tick
(with no hand on it, the rest shape); a damped balloon and the FEM solid relax from it.

Nothing here opens a socket or runs on the simulation tick: snapshots are taken only at a drain.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import time
import zipfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from haptic_collab.shared.types import FloatArray

if TYPE_CHECKING:
    from haptic_collab.server.room import Room

log = logging.getLogger("haptic.server")

#: The snapshot file format's version; a file of another version is refused.
FORMAT_VERSION = 1
#: A room's snapshot file is ``NAME`` + this.
SUFFIX = ".npz"
#: A snapshot being loaded (claimed), loaded, or refused: ``NAME.npz`` + this.
LOADING, LOADED, REFUSED = ".loading", ".loaded", ".refused"
#: The largest difference [m] between the surface a restored state shows and the surface the
#: file recorded; the state is recomputed exactly the way a step makes it, so it is 0 unless
#: the state does not belong to this object.
SURFACE_TOL_M = 1e-9
#: Parameters that are not physics (a memory budget): left out of ``params_sha256``.
_NOT_PHYSICS = frozenset({"cache_mb"})
#: The description's keys (:func:`describe`).
_DESCRIPTION = (
    "object_kind",
    "n_vertices",
    "n_faces",
    "mesh_sha256",
    "volume_sha256",
    "params_sha256",
)


class SnapshotError(ValueError):
    """A snapshot that cannot be used; the message says why."""


@dataclass(frozen=True)
class Snapshot:
    """One room's state, taken at a drain (:func:`capture`) and written by :func:`write`.

    Attributes
    ----------
    room : str
        The room's name.
    tick : int
        The last simulation tick the room ran.
    description : mapping of str to str or int
        :func:`describe` of its object.
    vertices : (n, 3) float64 [m]
        The surface shown.
    state : mapping of str to ndarray
        :func:`object_state` of its object (copies).
    """

    room: str
    tick: int
    description: Mapping[str, str | int]
    vertices: FloatArray
    state: Mapping[str, np.ndarray]


def snapshot_path(directory: str | Path, room: str) -> Path:
    """``DIRECTORY/ROOM.npz``: where room ``room``'s snapshot is written and looked for."""
    return Path(directory) / f"{room}{SUFFIX}"


def check_directory(directory: str | Path) -> Path:
    """Make the snapshot directory if needed and check that a file can be written in it (at the
    start, so that a bad path fails the start and not the drain).

    Raises
    ------
    ValueError
        It cannot be made, is not a directory, or a file cannot be written in it.
    """
    path = Path(directory).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise ValueError(f"--snapshot-dir {directory}: cannot write there: {exc}") from None
    return path


def _sha256(*arrays: np.ndarray) -> str:
    digest = hashlib.sha256()
    for arr in arrays:
        a = np.ascontiguousarray(arr)
        digest.update(f"{a.dtype.str}{a.shape}".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def _kind(obj: Any) -> str:
    from haptic_collab.server.objects.balloon import Balloon
    from haptic_collab.server.objects.fem import FemSolid

    if isinstance(obj, FemSolid):
        return "fem"
    if isinstance(obj, Balloon):
        return "balloon"
    return type(obj).__name__


def describe(obj: Any) -> dict[str, str | int]:
    """What identifies an object's state: its kind, sizes and hashes (module docstring).

    Parameters
    ----------
    obj : AdmittanceObject
        A :class:`server.objects.balloon.Balloon` or :class:`server.objects.fem.FemSolid`.

    Returns
    -------
    dict
        ``object_kind``, ``n_vertices``, ``n_faces``, ``mesh_sha256``, ``volume_sha256``,
        ``params_sha256``.
    """
    rest = np.asarray(obj.rest_vertices, dtype=np.float64)
    faces = np.asarray(obj.faces, dtype=np.int32)
    nodes, tets = getattr(obj, "nodes", None), getattr(obj, "tets", None)
    volume = ""
    if nodes is not None and tets is not None:
        volume = _sha256(np.asarray(nodes, np.float64), np.asarray(tets, np.int64))
    params = getattr(obj, "params", None)
    physics = ""
    if params is not None and dataclasses.is_dataclass(params):
        physics = repr(
            [(f.name, getattr(params, f.name)) for f in dataclasses.fields(params)
             if f.name not in _NOT_PHYSICS]
        )  # fmt: skip
    return {
        "object_kind": _kind(obj),
        "n_vertices": int(len(rest)),
        "n_faces": int(len(faces)),
        "mesh_sha256": _sha256(rest, faces),
        "volume_sha256": volume,
        "params_sha256": hashlib.sha256(physics.encode()).hexdigest(),
    }


def object_state(obj: Any) -> dict[str, np.ndarray]:
    """The object's dynamic state (copies): ``obj.state()`` (the balloon's normal displacement
    ``w`` (n,) [m]; the FEM solid's, :meth:`server.objects.fem.FemSolid.state`).

    Raises
    ------
    SnapshotError
        An object whose state this module does not know.
    """
    state = getattr(obj, "state", None)
    if callable(state):
        return {k: np.array(v, dtype=np.float64) for k, v in state().items()}
    raise SnapshotError(f"no snapshot for a {type(obj).__name__} object")


def set_object_state(obj: Any, state: Mapping[str, np.ndarray]) -> None:
    """Give the object a state :func:`object_state` took of the same object.

    Raises
    ------
    SnapshotError
        A key missing or extra, an array of another shape, a non-finite value.
    """
    setter = getattr(obj, "set_state", None)
    if not callable(setter):
        raise SnapshotError(f"no snapshot for a {type(obj).__name__} object")
    try:
        setter(state)
    except ValueError as exc:
        raise SnapshotError(str(exc)) from None


def capture(name: str, room: Room) -> Snapshot:
    """Room ``name``'s state now (copies; call it between ticks, on the room's thread).

    Raises
    ------
    SnapshotError
        As :func:`object_state`.
    """
    obj = room.world.obj
    return Snapshot(
        room=name,
        tick=int(room.tick_count),
        description=describe(obj),
        vertices=np.array(room.world.vertices, dtype=np.float64),
        state=object_state(obj),
    )


def write(directory: str | Path, snap: Snapshot) -> Path:
    """Write ``snap`` to ``DIRECTORY/ROOM.npz`` atomically (module docstring); returns the path.

    Raises
    ------
    OSError
        The directory cannot be written (the temporary file is removed).
    """
    target = snapshot_path(directory, snap.room)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    arrays: dict[str, np.ndarray] = {
        "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
        "room": np.array(snap.room),
        "tick": np.array(snap.tick, dtype=np.int64),
        "written_unix_s": np.array(time.time(), dtype=np.float64),
        "vertices": np.asarray(snap.vertices, dtype=np.float64),
    }
    for key in _DESCRIPTION:
        value = snap.description[key]
        arrays[key] = np.array(value, dtype=np.int64) if isinstance(value, int) else np.array(value)
    for key, part in snap.state.items():
        arrays[f"state_{key}"] = np.asarray(part, dtype=np.float64)
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)  # type: ignore[arg-type]
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _sync_directory(target.parent)
    return target


def write_all(directory: str | Path, snaps: Iterable[Snapshot]) -> list[Path]:
    """Write every snapshot (:func:`write`); one that cannot be written is logged and skipped.

    Returns the paths written.
    """
    written = []
    for snap in snaps:
        try:
            written.append(write(directory, snap))
        except OSError as exc:
            log.error(
                "room %r: its snapshot could not be written to %s: %s", snap.room, directory, exc
            )
    return written


def _sync_directory(directory: Path) -> None:
    """Flush a directory's entries (the rename) to disk where the platform allows it."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _scalar(z: Any, key: str, kind: type) -> Any:
    if key not in z.files:
        raise SnapshotError(f"no {key!r} in the file")
    arr = z[key]
    if arr.shape != ():
        raise SnapshotError(f"{key!r} is not a single value")
    value = arr.item()
    if not isinstance(value, kind) or isinstance(value, bool):
        raise SnapshotError(f"{key!r} is {value!r}, not a {kind.__name__}")
    return value


def read(path: str | Path) -> Snapshot:
    """Read a snapshot file (without pickle) and check its format.

    Raises
    ------
    SnapshotError
        Not a readable ``.npz``, another format version, a field missing or of the wrong kind.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            version = _scalar(z, "format_version", int)
            if version != FORMAT_VERSION:
                raise SnapshotError(
                    f"format version {version}, this server reads version {FORMAT_VERSION}"
                )
            description: dict[str, str | int] = {}
            for key in _DESCRIPTION:
                description[key] = _scalar(z, key, int if key.startswith("n_") else str)
            if "vertices" not in z.files:
                raise SnapshotError("no 'vertices' in the file")
            state = {k.removeprefix("state_"): z[k] for k in z.files if k.startswith("state_")}
            return Snapshot(
                room=_scalar(z, "room", str),
                tick=_scalar(z, "tick", int),
                description=description,
                vertices=np.asarray(z["vertices"], dtype=np.float64),
                state=state,
            )
    except SnapshotError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise SnapshotError(f"not a readable snapshot ({type(exc).__name__}: {exc})") from None


def check(snap: Snapshot, name: str, obj: Any) -> None:
    """Refuse a snapshot that is not room ``name``'s or not of this object.

    Raises
    ------
    SnapshotError
        Another room's, another object's (kind, mesh, volume mesh, parameters), a state or
        surface of the wrong shape, a negative tick.
    """
    if snap.room != name:
        raise SnapshotError(f"it is room {snap.room!r}'s")
    if snap.tick < 0:
        raise SnapshotError(f"tick {snap.tick} is negative")
    mine = describe(obj)
    for key in _DESCRIPTION:
        if snap.description[key] != mine[key]:
            what = str(snap.description[key])[:16]
            raise SnapshotError(
                f"it is of another object: {key} {what} where this room's is {str(mine[key])[:16]}"
            )
    if snap.vertices.shape != (mine["n_vertices"], 3):
        raise SnapshotError(f"its surface has shape {snap.vertices.shape}")


def restore(directory: str | Path, name: str, room: Room) -> bool:
    """Start room ``name`` from its snapshot in ``directory``, if there is one; never raises.

    The file is claimed (renamed ``.loading``), read, checked (:func:`check`), its state given to
    the room's object, and the surface it then shows compared with the file's (at most
    :data:`SURFACE_TOL_M` apart); the room's tick goes on from the file's. Then the file becomes
    ``.loaded``. Anything wrong: the object is put back at rest, the file becomes ``.refused``,
    and a warning says why. Call it before the room's simulation starts.

    Returns
    -------
    bool
        Whether the room starts from the snapshot.
    """
    path = snapshot_path(directory, name)
    claimed = path.with_name(path.name + LOADING)
    try:
        os.replace(path, claimed)
    except FileNotFoundError:
        return False  # no snapshot: the room starts from rest, as always
    except OSError as exc:
        log.warning(
            "room %r: snapshot %s cannot be claimed (%s); starting from rest", name, path, exc
        )
        return False
    world = room.world
    obj: Any = world.obj
    try:
        snap = read(claimed)
        check(snap, name, obj)
        set_object_state(obj, snap.state)
        shown = np.asarray(obj.vertices, dtype=np.float64)
        off = float(np.max(np.abs(shown - snap.vertices))) if len(shown) else 0.0
        if not off <= SURFACE_TOL_M:
            raise SnapshotError(f"its state shows a surface {off:.3g} m off the one it recorded")
    except Exception as exc:  # noqa: BLE001 - never crash a room's start on a file
        obj.reset()
        world.restore(room.tick_count)
        _settle(claimed, REFUSED)
        reason = str(exc) if isinstance(exc, SnapshotError) else f"{type(exc).__name__}: {exc}"
        log.warning(
            "room %r: snapshot %s refused (%s); the room starts from rest (the file is now %s)",
            name,
            path,
            reason,
            path.name + REFUSED,
        )
        return False
    room.restored(snap.tick)
    _settle(claimed, LOADED)
    log.info(
        "room %r: started from snapshot %s (tick %d, largest displacement %.3g mm; the file is "
        "now %s)",
        name,
        path,
        snap.tick,
        1e3 * float(obj.max_displacement_m),
        path.name + LOADED,
    )
    return True


def _settle(claimed: Path, suffix: str) -> None:
    """Rename a claimed snapshot ``NAME.npz.loading`` to ``NAME.npz`` + ``suffix``."""
    base = claimed.name.removesuffix(LOADING)
    try:
        os.replace(claimed, claimed.with_name(base + suffix))
    except OSError as exc:
        log.warning("snapshot %s could not be renamed to %s: %s", claimed, base + suffix, exc)
