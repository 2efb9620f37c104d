"""Where a server is reachable: the URLs to print for a bind address (stdlib only, no traffic).

``haptic server`` and ``haptic demo`` print the viewer's URLs with :func:`viewer_urls`: a wildcard
bind (``0.0.0.0``, ``::``) lists loopback and this machine's LAN addresses, never ``0.0.0.0``.
"""

from __future__ import annotations

import contextlib
import socket

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
