"""Device backends: the plug-in point behind ``--device NAME:ARGS`` (docs/devices.md).

A *backend* turns the text of a ``--device`` spec into a :class:`~client.devices.base.Device`.
The spec's prefix (before the first ``:``) names the backend; the rest (``ARGS``) is the
backend's own business. Backends are found through the entry-point group
:data:`ENTRY_POINT_GROUP` (``haptic_collab.devices``): each entry point's name is a spec prefix and
its value points to a backend object (or a class, called with no arguments). A lab adds its own
device by installing a package that declares one::

    [project.entry-points."haptic_collab.devices"]
    labdev = "labpkg:BACKEND"

The built-in ``sim`` and ``hid`` backends are declared the same way in this package's
pyproject.toml and are also found through :data:`BUILTIN_BACKENDS` when no entry point names them
(a source checkout that was not reinstalled).

How the client uses a backend (:class:`client.devices.opener.DeviceOpener`):

1. before any network: :meth:`DeviceBackend.available` (a message is a :class:`DeviceError`),
   then :meth:`DeviceBackend.open` with the ``ARGS`` text and the :class:`DeviceOptions`;
2. after the server's ``welcome``: :meth:`DeviceBackend.place` with the object's anchor and
   outward normal, then :meth:`Device.open` on the device it returns;
3. a device never placed (the client stopped before the welcome) is released with
   :meth:`Device.close`.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from pydantic import ValidationError

from haptic_collab.client.devices.base import Device, Vec3
from haptic_collab.shared.checks import describe

if TYPE_CHECKING:
    from haptic_collab.client.devices.hid import HidPort
    from haptic_collab.client.devices.profiles import HidProfile
    from haptic_collab.client.devices.sim import HandParams

__all__ = [
    "BUILTIN_BACKENDS",
    "DeviceBackend",
    "DeviceError",
    "DeviceOpenError",
    "DeviceOptions",
    "ENTRY_POINT_GROUP",
    "HID_STANDOFF_M",
    "PLACEHOLDER_ANCHOR",
    "PLACEHOLDER_NORMAL",
    "backend_names",
    "get_backend",
    "list_backends",
    "one_line",
    "usable_backend",
]

#: The entry-point group device backends register in; an entry point's name is a spec prefix.
ENTRY_POINT_GROUP = "haptic_collab.devices"

#: The built-in backends, as their entry points in pyproject.toml say (``module:attribute``);
#: used for a name no installed entry point provides.
BUILTIN_BACKENDS: dict[str, str] = {
    "hid": "haptic_collab.client.devices.hid_backend:HID_BACKEND",
    "sim": "haptic_collab.client.devices.sim_backend:SIM_BACKEND",
    "openhaptics": "haptic_collab.client.devices.openhaptics:BACKEND",
    "forcedimension": "haptic_collab.client.devices.forcedimension:BACKEND",
    "haply": "haptic_collab.client.devices.haply:BACKEND",
}

#: What every backend object has (:class:`DeviceBackend`).
BACKEND_MEMBERS = ("name", "description", "available", "detect", "open", "place")

#: Distance [m] outside the anchor of a HID device's workspace centre (the vendor backends place
#: theirs the same way: :mod:`client.devices._vendor`).
HID_STANDOFF_M = 0.02

#: Where :meth:`DeviceBackend.open` builds a device before the server says where the object is
#: (:meth:`DeviceBackend.place` builds or moves it around the real anchor after the welcome).
PLACEHOLDER_ANCHOR: Vec3 = (0.0, 0.0, 0.0)
PLACEHOLDER_NORMAL: Vec3 = (0.0, 0.0, 1.0)


class DeviceError(ValueError):
    """A device spec that cannot be used, or a device that cannot be opened.

    The message is one line: what is wrong and what to do (``haptic client`` prints it and
    exits 2 before connecting to any server).
    """


class DeviceOpenError(OSError):
    """An ``OSError`` from :meth:`Device.open` whose message is already the whole line to show.

    :class:`client.devices.opener.DeviceOpener` shows any other ``OSError`` from
    :meth:`Device.open` as ``cannot open SPEC: <the error>``; raise this one to say it your own way
    (what is wrong and what to do, starting with ``cannot open SPEC:``).
    """


def one_line(text: object) -> str:
    """``text`` as one line: its non-blank lines stripped and joined with ``; ``.

    A parameter class's :class:`pydantic.ValidationError` gives its first problem,
    ``FIELD must be BOUND, got VALUE`` (:func:`shared.checks.describe`), not pydantic's lines.
    """
    if isinstance(text, ValidationError):
        return describe(text)
    return "; ".join(part.strip() for part in str(text).splitlines() if part.strip())


@dataclass(frozen=True)
class DeviceOptions:
    """What the client knows about the device besides the spec (``haptic client`` options).

    A backend uses what applies to it and ignores the rest.

    Attributes
    ----------
    profile : str
        ``--profile``: the simulated device profile (``phantom-desktop``, ``touch``).
    trajectory_options : mapping
        ``--trajectory`` and ``--hand-*`` values of a simulated hand (see
        :func:`client.devices.opener.make_device`).
    hand : HandParams or None
        The simulated hand (None: the default).
    servo_rate_hz : float
        Servo rate [Hz] the device is read and written at (default 1000).
    hid_profile : str, Path, HidProfile or None
        ``--hid-profile``: a generic HID profile (bundled name, file, or loaded).
    hid_opener : callable or None
        ``opener(vendor_id, product_id) -> port`` HID ports are opened with (None: hidapi;
        tests pass a fake).
    acquire : bool
        True when the client is about to run the device (``haptic client``, before it connects):
        make sure the hardware answers now, and keep hold of it, so that an absent or busy device
        fails before any network. False from :func:`client.devices.opener.make_device`, which only
        builds the device object (tests, benchmarks): do not touch the hardware.
    """

    profile: str = "phantom-desktop"
    trajectory_options: Mapping[str, float] = field(default_factory=dict)
    hand: HandParams | None = None
    servo_rate_hz: float = 1000.0
    hid_profile: str | Path | HidProfile | None = None
    hid_opener: Callable[[int, int], HidPort] | None = None
    acquire: bool = False


class DeviceBackend(Protocol):
    """What a device backend offers (docs/devices.md).

    Any object with these members works; subclass this class to inherit the defaults of
    :meth:`available` (usable), :meth:`detect` (nothing to list) and :meth:`place` (the device
    does not depend on where the object is).

    Attributes
    ----------
    name : str
        The spec prefix (the entry point's name), e.g. ``labdev`` for ``--device labdev:ARGS``.
    description : str
        One line for ``haptic devices``: what the device is and the form of ``ARGS``.
    """

    name: str
    description: str

    def available(self) -> str | None:
        """None when the backend can be used here; else one line: what is missing, what to install.

        Called before :meth:`open` and by ``haptic devices``; it must be cheap and must not
        raise (check that the vendor library imports, not that a device is plugged in).
        """
        return None

    def detect(self) -> list[dict[str, Any]]:
        """The devices attached now, as JSON-able dicts (``haptic devices``); may be empty.

        Give each a ``spec`` (what to pass to ``--device``) where you can; ``haptic devices``
        adds ``backend`` (this backend's name) and defaults ``kind`` to it.
        """
        return []

    @abstractmethod
    def open(self, args: str, options: DeviceOptions) -> Device:
        """The device ``NAME:args`` names, built before any network and not yet opened.

        Parse ``args`` and check everything that can be checked now; with ``options.acquire``,
        also make sure the hardware answers (and you may keep hold of it: release it in the
        device's :meth:`Device.close`, which the client calls if the device is never placed).
        :meth:`Device.open` is called later, on the device :meth:`place` returns.

        Raises
        ------
        DeviceError
            The device cannot be used: one line with what is wrong and what to do (any other
            ``ValueError`` is shown the same way).
        """

    def place(self, device: Device, anchor: Vec3, normal: Vec3) -> Device:
        """The device to run once the server's welcome says where the user works on the object.

        Parameters
        ----------
        device : Device
            What :meth:`open` returned (not opened).
        anchor : (3,) float
            Surface point [m] of the object, world frame.
        normal : (3,) float
            Outward unit surface normal at ``anchor``.

        Returns
        -------
        Device
            ``device`` itself (moved, e.g. its workspace centred near the anchor) or a new device
            built around the anchor that takes over what ``device`` held; not yet opened.

        Raises
        ------
        DeviceError
            The device cannot be placed there (one line).
        """
        return device


def _entry_points() -> dict[str, EntryPoint]:
    """The installed entry points of :data:`ENTRY_POINT_GROUP` by name (the first of each name)."""
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep)
    return found


def _ordered(names: set[str]) -> list[str]:
    """The built-in names first (their order), then the others sorted."""
    return [n for n in BUILTIN_BACKENDS if n in names] + sorted(names - set(BUILTIN_BACKENDS))


def backend_names() -> list[str]:
    """Every spec prefix one may use: the built-in backends, then the installed ones, sorted."""
    return _ordered(set(BUILTIN_BACKENDS) | set(_entry_points()))


def _load(ep: EntryPoint) -> DeviceBackend:
    """The backend an entry point points to (a class is called with no arguments).

    Raises
    ------
    DeviceError
        It cannot be imported, or it is not a backend.
    """
    try:
        obj = ep.load()
        if isinstance(obj, type):
            obj = obj()
    except Exception as exc:  # an entry point runs a third party's code: say which one failed
        raise DeviceError(
            f"cannot load device backend {ep.name!r} ({ep.value}): {one_line(exc) or type(exc).__name__}; "
            "reinstall the package that provides it"
        ) from None
    missing = [m for m in BACKEND_MEMBERS if not hasattr(obj, m)]
    if missing:
        raise DeviceError(
            f"device backend {ep.name!r} ({ep.value}) is not a backend: it has no "
            f"{', '.join(missing)} (see docs/devices.md)"
        )
    backend: DeviceBackend = obj
    return backend


def unknown_backend_message(spec: str) -> str:
    """The one line for a spec whose prefix no backend has."""
    name = spec.partition(":")[0]
    return (
        f"unknown device spec {spec!r}: no device backend {name!r}; known backends: "
        f"{', '.join(backend_names())} (e.g. sim:press, sim:rest, sim:replay:FILE, hid:VID:PID); "
        "`haptic devices` lists them, docs/devices.md says how to add one"
    )


def get_backend(name: str, spec: str | None = None) -> DeviceBackend:
    """The backend for a spec prefix: its installed entry point, else the built-in one.

    A built-in name whose entry point cannot be loaded (a stale installation) falls back to the
    built-in backend.

    Parameters
    ----------
    name : str
        The spec prefix.
    spec : str, optional
        The whole spec, quoted in the error (default ``name``).

    Raises
    ------
    DeviceError
        No backend has this name (the message lists the known ones), or its entry point cannot
        be loaded.
    """
    ep = _entry_points().get(name)
    if ep is not None:
        try:
            return _load(ep)
        except DeviceError:
            if name not in BUILTIN_BACKENDS:
                raise
    if name in BUILTIN_BACKENDS:
        return _load(EntryPoint(name=name, value=BUILTIN_BACKENDS[name], group=ENTRY_POINT_GROUP))
    raise DeviceError(unknown_backend_message(spec if spec is not None else name))


def usable_backend(spec: str) -> tuple[DeviceBackend, str]:
    """The backend of ``spec`` (``NAME`` or ``NAME:ARGS``) and its ``ARGS``, checked usable.

    Raises
    ------
    DeviceError
        Unknown prefix, a backend that cannot be loaded, or one whose :meth:`available` says
        what is missing (that message, as one line).
    """
    name, _, args = spec.partition(":")
    backend = get_backend(name, spec)
    try:
        missing = backend.available()
    except Exception as exc:  # a third party's check that fails is a backend that is not usable
        missing = f"device backend {name!r}: available() failed: {one_line(exc)}"
    if missing:
        raise DeviceError(one_line(missing))
    return backend, args


def list_backends() -> list[dict[str, Any]]:
    """One entry per backend (``haptic devices``): the built-in ones first, then the installed.

    Returns
    -------
    list of dict
        ``name``, ``spec`` (``NAME:``), ``description``, ``available`` (bool), ``message``
        (None, or what is missing), ``entry_point`` (``module:attribute``, None for a built-in
        found without one) and ``devices`` (what :meth:`DeviceBackend.detect` found, each with
        ``spec``, ``kind`` and ``backend``; empty when the backend is not available). A backend
        that cannot be loaded, or whose detection fails, is listed with the error as its message.
    """
    eps = _entry_points()
    out: list[dict[str, Any]] = []
    for name in _ordered(set(BUILTIN_BACKENDS) | set(eps)):
        entry: dict[str, Any] = {
            "name": name,
            "spec": f"{name}:",
            "description": "",
            "available": False,
            "message": None,
            "entry_point": eps[name].value if name in eps else None,
            "devices": [],
        }
        out.append(entry)
        try:
            backend = get_backend(name)
        except DeviceError as exc:
            entry["message"] = str(exc)
            continue
        entry["description"] = one_line(getattr(backend, "description", ""))
        try:
            missing = backend.available()
        except Exception as exc:  # listing must not die on one broken backend
            missing = f"available() failed: {one_line(exc)}"
        if missing:
            entry["message"] = one_line(missing)
            continue
        entry["available"] = True
        try:
            found = [dict(d) for d in backend.detect()]
        except Exception as exc:  # listing must not die on one broken backend
            entry["message"] = f"detect() failed: {one_line(exc)}"
            continue
        for d in found:
            d.setdefault("spec", f"{name}:")
            d.setdefault("kind", name)
            d.setdefault("backend", name)
        entry["devices"] = found
    return out
