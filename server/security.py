"""Who may connect, and how much any one source may cost: tokens, origins, per-address budgets.

Pure code, no sockets and no clocks (times are inputs), so the room and the tests drive it alone.

Token file format (``haptic server --token-file FILE``), one token per line::

    # comment lines and blank lines are ignored
    TOKEN ROLE [NAME]

``ROLE`` is ``user`` (may push, and may also watch) or ``viewer`` (may only watch). ``NAME``, when
given, binds the token to that name: a connection with this token is always called ``NAME``, and
no other connection may take it. A token is 16-256 printable characters without spaces or ``#``;
make one with ``python -c "import secrets; print(secrets.token_urlsafe(24))"``.

Room tokens (``haptic server --token-secret-file FILE``; made with ``haptic token``) are signed
and expire: ``hcr1.ROOM.ROLE.EXPIRES.MAC`` with an HMAC-SHA256 over room, role and expiry under
the server's secret (:func:`make_room_token`, :func:`check_room_token`, :class:`RoomTokens`). A
room token is valid only in its room, only in its role, and only until it expires; the
server-wide tokens above stay valid in every room.

Resume tokens (:func:`new_resume_token`) are not access tokens: each user's ``welcome`` carries
one, good once, for getting its own seat back in the same room after a dropped link
(:meth:`server.room.Room.disconnect`); the room keeps their SHA-256 digests only and compares
them in constant time (:func:`resume_matches`). They never replace the access token a ``hello``
needs.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import math
import re
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

Role = Literal["user", "viewer"]

#: Shortest token accepted from a token file or ``--token`` [characters].
MIN_TOKEN_CHARS = 16
_TOKEN_RE = re.compile(r"^[!-~]{16,256}$")
_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,32}$")


@dataclass(frozen=True)
class TokenEntry:
    """One token's rights: its role and, optionally, the name bound to it."""

    role: Role
    name: str | None = None
    digest: bytes = b""

    def __repr__(self) -> str:  # never show the token (nor its digest) in logs
        return f"TokenEntry(role={self.role!r}, name={self.name!r})"


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).digest()


def _check_token(token: str, where: str) -> None:
    if not _TOKEN_RE.match(token) or "#" in token:
        raise ValueError(
            f"{where}: a token is {MIN_TOKEN_CHARS}-256 printable characters without spaces or #"
        )


class TokenTable:
    """The tokens a server accepts, each with a role and an optional bound name.

    Tokens are kept as SHA-256 digests and compared with :func:`hmac.compare_digest` against every
    entry (no early exit), so neither the comparison nor the lookup leaks how much of a guess
    was right.

    Parameters
    ----------
    entries : dict of str to (role, name or None)
        Token -> rights.

    Raises
    ------
    ValueError
        A malformed token, role or name, or a name bound to two tokens.
    """

    def __init__(self, entries: dict[str, tuple[Role, str | None]]) -> None:
        names: set[str] = set()
        self._entries: list[TokenEntry] = []
        for token, (role, name) in entries.items():
            _check_token(token, "token")
            if role not in ("user", "viewer"):
                raise ValueError(f"token role must be 'user' or 'viewer', got {role!r}")
            if name is not None:
                if not _NAME_RE.match(name):
                    raise ValueError(f"bound name {name!r} must be 1-32 of A-Za-z0-9_.-")
                if name in names:
                    raise ValueError(f"name {name!r} is bound to two tokens")
                names.add(name)
            self._entries.append(TokenEntry(role, name, _digest(token)))
        if not self._entries:
            raise ValueError("no tokens given")
        self.bound_names = frozenset(names)

    def __len__(self) -> int:
        return len(self._entries)

    @classmethod
    def single(cls, token: str) -> TokenTable:
        """One token with role ``user`` (``haptic server --token``)."""
        return cls({token: ("user", None)})

    @classmethod
    def parse(cls, text: str, source: str = "token file") -> TokenTable:
        """Parse the ``TOKEN ROLE [NAME]`` lines of a token file (see the module docstring).

        Raises
        ------
        ValueError
            A malformed line (its number is given, never its token) or a repeated token.
        """
        entries: dict[str, tuple[Role, str | None]] = {}
        for number, raw in enumerate(text.splitlines(), start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            where = f"{source} line {number}"
            if len(parts) not in (2, 3):
                raise ValueError(f"{where}: expected 'TOKEN ROLE [NAME]'")
            token, role = parts[0], parts[1]
            _check_token(token, where)
            if role not in ("user", "viewer"):
                raise ValueError(f"{where}: role must be 'user' or 'viewer', got {role!r}")
            if token in entries:
                raise ValueError(f"{where}: the same token appears twice")
            entries[token] = (role, parts[2] if len(parts) == 3 else None)  # type: ignore[assignment]
        if not entries:
            raise ValueError(f"{source}: no tokens (lines 'TOKEN ROLE [NAME]')")
        return cls(entries)

    @classmethod
    def load(cls, path: str | Path) -> TokenTable:
        """Read a token file. Raises ``ValueError`` (unreadable or malformed file)."""
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise ValueError(f"cannot read token file {path}: {exc.strerror or exc}") from None
        return cls.parse(text, source=str(path))

    def check(self, token: str | None) -> TokenEntry | None:
        """The rights of ``token``, or None when it is missing or unknown (constant time)."""
        if token is None:
            return None
        digest = _digest(token)
        found: TokenEntry | None = None
        for entry in self._entries:  # every entry, no early exit
            if hmac.compare_digest(digest, entry.digest):
                found = entry
        return found


def is_loopback(host: str) -> bool:
    """True when ``host`` (an address or name the server binds to) reaches only this machine."""
    h = host.strip().strip("[]").lower()
    if h in ("localhost", "localhost.", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def origin_allowed(
    origin: str | None, host_header: str | None, allowed: frozenset[str], loopback_only: bool
) -> bool:
    """Whether a websocket handshake with this ``Origin`` may proceed.

    Allowed: no ``Origin`` (not a browser: browsers always send one); an origin in ``allowed``
    (``--allow-origin``); or the server's own origin, i.e. the page was served by this server:
    the origin's ``host:port`` equals the request's ``Host``. A server bound to loopback also
    requires that host to be a loopback name, which defeats DNS rebinding (a hostile name that
    resolves to 127.0.0.1 has the same origin as the page it served).

    Parameters
    ----------
    origin : str or None
        The ``Origin`` header, e.g. ``http://localhost:8765``.
    host_header : str or None
        The ``Host`` header of the same request.
    allowed : frozenset of str
        Extra origins allowed, as ``scheme://host[:port]`` (``*`` allows every origin).
    loopback_only : bool
        The server is bound to a loopback address.
    """
    if origin is None:
        return True
    origin = origin.strip()
    if "*" in allowed or origin.rstrip("/") in allowed:
        return True
    if origin == "null" or host_header is None:
        return False
    parts = urlsplit(origin)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        return False
    own = _netloc(parts.netloc, parts.scheme) == _netloc(host_header.strip(), parts.scheme)
    if not own:
        return False
    return not loopback_only or is_loopback(parts.hostname or "")


def _netloc(netloc: str, scheme: str) -> str:
    """``host:port`` with the scheme's default port made explicit, lower case."""
    n = netloc.lower().rsplit("@", 1)[-1]
    if n.endswith("]") or ":" not in n.rsplit("]", 1)[-1]:
        n += ":443" if scheme == "https" else ":80"
    return n


def normalize_origin(origin: str) -> str:
    """An ``--allow-origin`` value checked and without a trailing slash.

    Raises
    ------
    ValueError
        Not ``*`` and not ``http(s)://host[:port]``.
    """
    o = origin.strip().rstrip("/")
    if o == "*":
        return o
    parts = urlsplit(o)
    if parts.scheme not in ("http", "https") or not parts.netloc or parts.path:
        raise ValueError(f"--allow-origin wants scheme://host[:port], got {origin!r}")
    return o


class TokenBucket:
    """A token bucket: ``rate`` units per second, at most ``burst`` saved up; time is an input.

    :meth:`lift` refills a stretch of time without the ``burst`` cap: the server was behind its
    own schedule then and read nothing, so what a client sent meanwhile arrives at once and must
    be charged as if it had been read on time (:meth:`server.room.Room.behind_schedule`). The
    level above ``burst`` is kept until ``lifted_until_s`` [s], then cut back to ``burst``.

    Parameters
    ----------
    rate : float
        Sustained units per second (frames/s or bytes/s), > 0.
    burst : float
        Bucket size (units), > 0.
    now_s : float
        Creation time [s]; the bucket starts full.
    """

    __slots__ = ("rate", "burst", "level", "at_s", "lifted_until_s")

    def __init__(self, rate: float, burst: float, now_s: float) -> None:
        self.rate = float(rate)
        self.burst = float(burst)
        self.level = float(burst)
        self.at_s = float(now_s)
        self.lifted_until_s = -math.inf

    def refill(self, now_s: float) -> float:
        """Bring the level up to time ``now_s`` [s]; returns the level."""
        if now_s > self.at_s:
            if self.level > self.burst and now_s > self.lifted_until_s:
                self.level = self.burst  # a stall's credit lapsed unspent
            if self.level < self.burst:
                self.level = min(self.burst, self.level + (now_s - self.at_s) * self.rate)
            self.at_s = now_s
        return self.level

    def take(self, amount: float, now_s: float) -> bool:
        """Take ``amount`` units at ``now_s`` [s] if available; False (nothing taken) otherwise."""
        if self.refill(now_s) < amount:
            return False
        self.level -= amount
        return True

    def lift(self, from_s: float, to_s: float, keep_until_s: float, max_extra_s: float) -> None:
        """Refill the stretch ``[from_s, to_s]`` [s] without the ``burst`` cap.

        Only the part of the stretch after the bucket's last update counts (no time is credited
        twice), so a bucket that was being spent meanwhile gains exactly what :meth:`refill`
        would have given it; only a bucket that would have hit ``burst`` gains more. The level
        stays at most ``burst + rate * max_extra_s``; what lies above ``burst`` lapses after
        ``keep_until_s`` [s].
        """
        self.refill(from_s)
        start = max(self.at_s, from_s)
        if to_s <= start:
            return
        top = self.burst + self.rate * max(0.0, max_extra_s)
        self.level = max(self.level, min(top, self.level + (to_s - start) * self.rate))
        self.at_s = to_s
        self.lifted_until_s = max(self.lifted_until_s, keep_until_s)

    @property
    def fill(self) -> float:
        """Level over size: 1 when full, lower when spent (above 1 while a stall is credited)."""
        return self.level / self.burst


# ------------------------------------------------------------------------------ room tokens
#: The first field of a room token (its format's version).
ROOM_TOKEN_PREFIX = "hcr1"
#: The shortest token secret accepted [bytes of the file, whitespace stripped].
MIN_SECRET_BYTES = 32
#: The longest lifetime a room token may be made with [s] (30 days).
MAX_TOKEN_TTL_S = 30 * 24 * 3600.0
_ROOM_TOKEN_RE = re.compile(
    r"^hcr1\.(?P<room>[a-z0-9](?:[a-z0-9-]{0,30}[a-z0-9])?)\.(?P<role>user|viewer)"
    r"\.(?P<exp>[0-9]{1,12})\.(?P<mac>[0-9a-f]{64})$"
)


def load_secret(path: str | Path) -> bytes:
    """The token secret of a file: its bytes with surrounding whitespace stripped.

    Make one with ``python -c "import secrets; print(secrets.token_urlsafe(48))" > FILE``.

    Raises
    ------
    ValueError
        A file that cannot be read, or a secret shorter than :data:`MIN_SECRET_BYTES` bytes (the
        message never shows the file's content).
    """
    try:
        secret = Path(path).read_bytes().strip()
    except OSError as exc:
        raise ValueError(
            f"cannot read the token secret file {path}: {exc.strerror or exc}"
        ) from None
    if len(secret) < MIN_SECRET_BYTES:
        raise ValueError(
            f"{path}: a token secret is at least {MIN_SECRET_BYTES} bytes (make one with "
            'python -c "import secrets; print(secrets.token_urlsafe(48))")'
        )
    return secret


def _room_mac(secret: bytes, room: str, role: str, expires: int) -> str:
    message = f"{ROOM_TOKEN_PREFIX}\n{room}\n{role}\n{expires}".encode()
    return hmac.new(secret, message, hashlib.sha256).hexdigest()


def make_room_token(secret: bytes, room: str, role: Role, expires_s: float) -> str:
    """A signed token for ``role`` in room ``room`` that expires at ``expires_s``.

    The token is ``hcr1.ROOM.ROLE.EXPIRES.MAC``: EXPIRES the Unix time [s, whole] after which it
    is refused, MAC the HMAC-SHA256 (RFC 2104) of the prefix, room, role and expiry under the
    server's ``secret``, in hex. Whoever holds the secret can make tokens; whoever holds a token
    can only join that room in that role until it expires. Nothing is stored on the server.

    Parameters
    ----------
    secret : bytes
        The server's token secret (:func:`load_secret`).
    room : str
        A room name (:func:`server.urls.valid_room_name`).
    role : {"user", "viewer"}
    expires_s : float
        Unix time [s] from which the token is refused (rounded down to a whole second).

    Raises
    ------
    ValueError
        A bad room name or role, an expiry that is not a finite time after 1970, or a secret
        shorter than :data:`MIN_SECRET_BYTES`.
    """
    if len(secret) < MIN_SECRET_BYTES:
        raise ValueError(f"a token secret is at least {MIN_SECRET_BYTES} bytes")
    if role not in ("user", "viewer"):
        raise ValueError(f"role must be 'user' or 'viewer', got {role!r}")
    if not (math.isfinite(expires_s) and 0 < expires_s < 1e12):
        raise ValueError(f"expiry must be a Unix time [s], got {expires_s!r}")
    expires = int(expires_s)
    token = f"{ROOM_TOKEN_PREFIX}.{room}.{role}.{expires}.{_room_mac(secret, room, role, expires)}"
    if not _ROOM_TOKEN_RE.match(token):
        raise ValueError(
            f"room name {room!r} must be 1-32 of a-z, 0-9 and -, starting and ending with a "
            "letter or digit"
        )
    return token


def check_room_token(token: str, secret: bytes, room: str, now_s: float) -> TokenEntry | None:
    """The rights of a room token in room ``room`` at Unix time ``now_s`` [s], or None.

    None when the token is not a room token, is for another room, has expired
    (``now_s >= EXPIRES``) or its MAC does not match (compared with
    :func:`hmac.compare_digest`). A token's room and role are in the signed message, so a token
    for room a cannot be turned into one for room b, nor a viewer's into a user's.
    """
    m = _ROOM_TOKEN_RE.match(token)
    if m is None:
        return None
    role, expires = m["role"], int(m["exp"])
    good = hmac.compare_digest(m["mac"], _room_mac(secret, m["room"], role, expires))
    if not good or m["room"] != room or not now_s < expires:
        return None
    return TokenEntry(role)  # type: ignore[arg-type]


class RoomTokens(TokenTable):
    """The tokens one room accepts: the server's :class:`TokenTable` and its room tokens.

    A room's ``auth`` (:class:`server.room.Room` asks :meth:`check` in every ``hello``): a
    server-wide token (``--token-file``, ``--token``) is valid in every room; a room token
    (:func:`make_room_token`, ``haptic token``) only in the room it names, and only until it
    expires. The expiry is checked against ``clock()`` (Unix time [s]: ``time.time`` in the
    server) when ``hello`` arrives; a connection already in stays in after its token expires.

    Parameters
    ----------
    room : str
        The room's name.
    table : TokenTable, optional
        The server-wide tokens (None: none).
    secret : bytes, optional
        The token secret (None: no room tokens).
    clock : callable
        Returns the current Unix time [s].

    Raises
    ------
    ValueError
        Neither a table nor a secret.
    """

    def __init__(
        self,
        room: str,
        table: TokenTable | None,
        secret: bytes | None,
        clock: Callable[[], float],
    ) -> None:
        if table is None and secret is None:
            raise ValueError("a room's tokens need a token table or a secret")
        self.room = room
        self._table = table
        self._secret = secret
        self._clock = clock
        self._entries = list(table._entries) if table is not None else []
        self.bound_names = table.bound_names if table is not None else frozenset()

    def __len__(self) -> int:
        return len(self._entries) + (1 if self._secret is not None else 0)

    def check(self, token: str | None) -> TokenEntry | None:
        """The rights of ``token`` in this room now, or None (missing, unknown, other room,
        expired)."""
        if token is None:
            return None
        if self._secret is not None and token.startswith(ROOM_TOKEN_PREFIX + "."):
            return check_room_token(token, self._secret, self.room, self._clock())
        return self._table.check(token) if self._table is not None else None


# ----------------------------------------------------------------------------- resume tokens
#: Random bytes in a resume token: 192 bits (at least 128 make guessing hopeless even for a
#: flood of attempts, each of which is a connection under the rate limits).
RESUME_TOKEN_BYTES = 24


def new_resume_token() -> tuple[str, bytes]:
    """A fresh resume token for one seat, and the digest the room keeps of it.

    The token is :data:`RESUME_TOKEN_BYTES` random bytes from :func:`secrets.token_urlsafe`
    (32 URL-safe characters): opaque and unguessable. The room keeps only its SHA-256 digest
    (as it does for the access tokens) and compares digests with :func:`resume_matches`.

    Returns
    -------
    token : str
        Sent once, in the user's ``welcome`` (``resume_token``); never logged.
    digest : bytes
        SHA-256 of the token (32 bytes).
    """
    token = secrets.token_urlsafe(RESUME_TOKEN_BYTES)
    return token, _digest(token)


def resume_digest(token: str) -> bytes:
    """SHA-256 digest of a resume token a ``hello`` presented (any string: no error)."""
    return _digest(token)


def resume_matches(digest: bytes, kept: bytes | None) -> bool:
    """Whether a presented token's ``digest`` is the ``kept`` one, in constant time.

    :func:`hmac.compare_digest` over two 32-byte digests: the time taken says nothing about
    how much of a guess was right. ``kept`` None (a seat without a token) never matches.
    """
    return kept is not None and hmac.compare_digest(digest, kept)
