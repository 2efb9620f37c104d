"""Who may connect, and how much any one source may cost: tokens, origins, per-address budgets.

Pure code, no sockets and no clocks (times are inputs), so the room and the tests drive it alone.

Token file format (``haptic server --token-file FILE``), one token per line::

    # comment lines and blank lines are ignored
    TOKEN ROLE [NAME]

``ROLE`` is ``user`` (may push, and may also watch) or ``viewer`` (may only watch). ``NAME``, when
given, binds the token to that name: a connection with this token is always called ``NAME``, and
no other connection may take it. A token is 16-256 printable characters without spaces or ``#``;
make one with ``python -c "import secrets; print(secrets.token_urlsafe(24))"``.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import math
import re
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
