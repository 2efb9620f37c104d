"""Where a server is reachable: the URLs to print for a bind address (stdlib only, no traffic).

``haptic server`` and ``haptic demo`` print the viewer's URLs with :func:`viewer_urls`: a wildcard
bind (``0.0.0.0``, ``::``) lists loopback and this machine's LAN addresses, never ``0.0.0.0``.

A server runs rooms by name (:func:`room_path`): ``/ws`` and ``/`` are the default room's
websocket and viewer page, ``/rooms/NAME/ws`` and ``/rooms/NAME/`` room NAME's (the viewer derives
its websocket URL from the page's path, web/viewer.js). A name is a short slug
(:func:`valid_room_name`).
"""

from __future__ import annotations

import contextlib
import re
import socket
from dataclasses import dataclass

#: Bind addresses that mean "every interface".
WILDCARD_HOSTS = frozenset({"", "0.0.0.0", "::"})


def local_host(host: str) -> str:
    """Where this machine reaches a server bound to ``host`` (loopback for a wildcard)."""
    if host in ("", "0.0.0.0"):
        return "127.0.0.1"
    if host == "::":
        return "::1"
    return host


def url_host(ip: str) -> str:
    return f"[{ip}]" if ":" in ip else ip


def reachable_addresses(host: str) -> list[str]:
    """The addresses a server bound to ``host`` is reachable at: loopback first, then the LAN's.

    A specific host is returned as it is. A wildcard (``0.0.0.0``, ``::`` or empty) gives the
    loopback address and this machine's non-loopback, non-link-local addresses: those of its
    host name (``socket.getaddrinfo(socket.gethostname())``) and the one of the interface the
    default route leaves by (a UDP socket "connected" to a documentation address, which sends
    nothing). Standard library only, no network traffic.

    Parameters
    ----------
    host : str
        The address the server binds.

    Returns
    -------
    list of str
        IP addresses (IPv6 without brackets), loopback first, no duplicates.
    """
    if host not in WILDCARD_HOSTS:
        return [host]
    v6 = host == "::"
    families = [socket.AF_INET6, socket.AF_INET] if v6 else [socket.AF_INET]
    found = ["::1", "127.0.0.1"] if v6 else ["127.0.0.1"]
    candidates: list[str] = []
    for fam in families:
        with contextlib.suppress(OSError, UnicodeError):
            for info in socket.getaddrinfo(socket.gethostname(), None, fam, socket.SOCK_STREAM):
                candidates.append(str(info[4][0]))
        probe = ("2001:db8::1", 9) if fam == socket.AF_INET6 else ("192.0.2.1", 9)
        with contextlib.suppress(OSError), socket.socket(fam, socket.SOCK_DGRAM) as s:
            s.connect(probe)  # UDP: picks the outgoing interface, sends nothing
            candidates.append(str(s.getsockname()[0]))
    for ip in candidates:
        ip = ip.split("%")[0]
        if ip.startswith(("127.", "169.254.", "fe80:", "0.")) or ip in ("::1", "::", "0.0.0.0"):
            continue
        if ip not in found:
            found.append(ip)
    return found


def viewer_urls(host: str, port: int, scheme: str = "http") -> list[str]:
    """Viewer URLs of a server bound to (host, port); a wildcard gives every reachable one.

    ``viewer_urls("0.0.0.0", 8765)`` is ``["http://127.0.0.1:8765/", "http://192.168.1.20:8765/",
    ...]`` (:func:`reachable_addresses`), never ``http://0.0.0.0:8765/``.
    """
    return [f"{scheme}://{url_host(ip)}:{port}/" for ip in reachable_addresses(host)]


#: The room ``/ws`` and ``/`` reach; the other rooms are under ``/rooms/<name>/``.
DEFAULT_ROOM = "default"
#: A room name: 1-32 of lower-case letters, digits and ``-``, starting and ending with a letter
#: or digit (a slug: safe in a URL path, a log line, a metrics label and an Agones list).
ROOM_NAME_RE = re.compile(r"^[a-z0-9](?:[a-z0-9-]{0,30}[a-z0-9])?$")
#: Where a room's pages and websocket live: ``/rooms/<name>/`` and ``/rooms/<name>/ws``.
ROOMS_PREFIX = "/rooms/"


def valid_room_name(name: str) -> bool:
    """Whether ``name`` is a room name (:data:`ROOM_NAME_RE`)."""
    return bool(ROOM_NAME_RE.match(name))


@dataclass(frozen=True)
class RoomPath:
    """An HTTP path split into the room it names and what it asks of that room.

    Attributes
    ----------
    room : str
        The room's name as written (check it with :func:`valid_room_name`).
    rest : str
        The path after the room's prefix: ``ws`` (its websocket), ``""`` (its viewer page) or
        another file of the viewer; ``None`` for ``/rooms/<name>`` without the slash (redirect).
    """

    room: str
    rest: str | None


def room_path(path: str) -> RoomPath | None:
    """The room a request path addresses, None when it is not a room's path.

    ``/ws`` and ``/`` are :data:`DEFAULT_ROOM`'s websocket and page; ``/rooms/NAME/ws`` and
    ``/rooms/NAME/`` are room NAME's. Any other path is None (static files, ``/status``...).
    The query string is ignored; the name is returned unchecked (see :func:`valid_room_name`).
    """
    path = path.split("?", 1)[0]
    if path in ("/ws", "/ws/"):
        return RoomPath(DEFAULT_ROOM, "ws")
    if not path.startswith(ROOMS_PREFIX):
        return None
    name, slash, rest = path[len(ROOMS_PREFIX) :].partition("/")
    if not slash:
        return RoomPath(name, None)
    return RoomPath(name, "ws" if rest == "ws/" else rest)


def room_ws_path(name: str) -> str:
    """The websocket path of room ``name`` (``/ws`` for :data:`DEFAULT_ROOM`)."""
    return "/ws" if name == DEFAULT_ROOM else f"{ROOMS_PREFIX}{name}/ws"


def room_page_path(name: str) -> str:
    """The viewer page's path of room ``name`` (``/`` for :data:`DEFAULT_ROOM`)."""
    return "/" if name == DEFAULT_ROOM else f"{ROOMS_PREFIX}{name}/"
