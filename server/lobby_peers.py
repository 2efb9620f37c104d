"""Several lobby replicas, each room name placed by one of them (:mod:`server.lobby`).

A lobby serialises the placements of one name in its own process. Replicas do not share that,
and the Agones allocator cannot do it for them: it matches selectors against a cache of the
GameServers that lags their writes, so two allocations for a new name that arrive together
(from two replicas, or through two allocator pods) can both miss the other's list entry and
land on two servers (``tests/support/agones_allocator.py`` reproduces this). So each name has
one owner among a fixed list of replicas (``--peer URL``, the same list on each), chosen by
rendezvous hashing (:meth:`Peers.owner`: the replica with the highest SHA-256 of its URL and
the name); a replica asked for a name it does not own asks the owner (``GET
/peer/place/NAME``, signed with an HMAC of the token secret the replicas share) and signs the
user's room token itself. Names move only when the list changes.

The price: while a name's owner is down (a restart takes seconds; the PodDisruptionBudget
keeps at most one replica down) a request for it is answered 503 with ``Retry-After``, never
placed by another replica. A StatefulSet gives the replicas the stable names the list needs
(``deploy/lobby/``).
"""

from __future__ import annotations

import hashlib
import hmac
import ssl
import time
from collections.abc import Sequence
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any
from urllib.parse import quote, urlsplit

from haptic_collab.server.lobby_backends import (
    LobbyError,
    Placement,
    _http_json,
    _in_pool,
    _timed_out,
)

#: The path a replica asks the owner of a name on (``/peer/place/NAME``).
PEER_PATH = "/peer/place/"
#: Lifetime of a peer request's signature [s] (the replicas' clocks agree to well within it).
PEER_SIGNATURE_TTL_S = 30
#: Time the owner may take to answer [s]: its own placement, which may build a room.
PEER_TIMEOUT_S = 70.0
_KEY_LABEL = b"haptic lobby peer v1"


def _key(secret: bytes) -> bytes:
    """The peers' HMAC key, derived from the token secret (never a valid room token's MAC)."""
    return hmac.new(secret, _KEY_LABEL, hashlib.sha256).digest()


def sign_peer_request(secret: bytes, name: str, expires_s: int) -> str:
    """The ``Authorization: Peer EXPIRES.MAC`` value of a request to place room ``name``."""
    mac = hmac.new(_key(secret), f"{name}\0{expires_s}".encode(), hashlib.sha256).hexdigest()
    return f"{expires_s}.{mac}"


def check_peer_request(secret: bytes, name: str, value: str, now_s: float) -> bool:
    """Whether ``value`` (:func:`sign_peer_request`) signs a request for ``name`` valid at
    ``now_s`` [s] (Unix time)."""
    expires, _, mac = value.strip().partition(".")
    if not expires.isdigit() or len(expires) > 12:
        return False
    if not 0 <= int(expires) - now_s <= 2 * PEER_SIGNATURE_TTL_S:
        return False
    return hmac.compare_digest(sign_peer_request(secret, name, int(expires)), value.strip())


def placement_json(placement: Placement) -> dict[str, Any]:
    """A :class:`Placement` as the owner's answer to a peer."""
    return {
        "ws_base": placement.ws_base,
        "http_base": placement.http_base,
        "server": placement.server,
        "created": placement.created,
        "full": placement.full,
    }


@dataclass(frozen=True)
class Peers:
    """The lobby replicas and which one this is.

    Parameters
    ----------
    urls : sequence of str
        Every replica, ``http(s)://HOST:PORT`` as the others reach it, the same list on each.
    self_url : str
        This replica's entry of ``urls``.
    context : ssl.SSLContext, optional
        TLS context for ``https://`` replicas (default: the system's CAs).
    timeout_s : float
        Time an owner may take to answer [s] (:data:`PEER_TIMEOUT_S`).

    Raises
    ------
    ValueError
        A URL that is not ``http(s)://HOST:PORT``, a repeated one, or ``self_url`` not among
        ``urls``.
    """

    urls: tuple[str, ...]
    self_url: str
    context: ssl.SSLContext | None = None
    timeout_s: float = PEER_TIMEOUT_S

    def __post_init__(self) -> None:
        urls = tuple(u.strip().rstrip("/") for u in self.urls)
        for url in urls:
            parts = urlsplit(url)
            if parts.scheme not in ("http", "https") or not parts.hostname or parts.path:
                raise ValueError(f"a lobby peer is http(s)://HOST:PORT, got {url!r}")
        if len(set(urls)) != len(urls):
            raise ValueError("a lobby peer is listed twice")
        me = self.self_url.strip().rstrip("/")
        if me not in urls:
            raise ValueError(f"this lobby ({me!r}) is not among its peers {list(urls)}")
        object.__setattr__(self, "urls", urls)
        object.__setattr__(self, "self_url", me)

    @classmethod
    def of(cls, urls: Sequence[str], self_url: str, **kw: Any) -> Peers:
        """:class:`Peers` of a list (a convenience for ``tuple(urls)``)."""
        return cls(tuple(urls), self_url, **kw)

    def owner(self, name: str) -> str:
        """The replica that places room ``name``: the highest SHA-256 of ``URL \\0 NAME``."""
        return max(self.urls, key=lambda u: hashlib.sha256(f"{u}\0{name}".encode()).digest())

    async def ask(self, owner: str, name: str, secret: bytes) -> Placement:
        """Have replica ``owner`` place room ``name``.

        Raises
        ------
        LobbyError
            The owner's refusal (its status and reason); 503 with ``Retry-After`` when it does
            not answer (down, restarting, or slower than ``timeout_s``).
        """
        signature = sign_peer_request(secret, name, int(time.time()) + PEER_SIGNATURE_TTL_S)
        try:
            code, answer = await _in_pool(
                _http_json, "GET", owner + PEER_PATH + quote(name, safe=""),
                timeout_s=self.timeout_s, context=self.context,
                headers={"Authorization": f"Peer {signature}"},
            )  # fmt: skip
        except OSError as exc:
            why = "does not answer in time" if _timed_out(exc) else "cannot be reached"
            raise LobbyError(
                HTTPStatus.SERVICE_UNAVAILABLE,
                f"the lobby replica that places room {name!r} ({owner}) {why}; try again",
                retry_after_s=2,
            ) from None
        if code == 200 and isinstance(answer, dict):
            try:
                return Placement(
                    str(answer["ws_base"]),
                    str(answer["http_base"]),
                    str(answer["server"]),
                    created=bool(answer.get("created")),
                    full=bool(answer.get("full")),
                )
            except KeyError:
                pass
        if code == HTTPStatus.NOT_FOUND and "GET /rooms/NAME" in str(answer):
            # the owner took it for a user's request: the signature did not check out there
            raise LobbyError(
                HTTPStatus.BAD_GATEWAY,
                f"the lobby replica {owner} refused this replica's request: do they share the "
                "token secret, and do their clocks agree within 30 s?",
            )
        if isinstance(answer, dict) and isinstance(answer.get("error"), str) and code >= 400:
            try:
                status = HTTPStatus(code)
            except ValueError:
                status = HTTPStatus.BAD_GATEWAY
            raise LobbyError(status, answer["error"])
        raise LobbyError(
            HTTPStatus.BAD_GATEWAY, f"the lobby replica {owner} answered {code} for {name!r}"
        )
