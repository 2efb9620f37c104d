"""The lobby's limits per client: who a request is from, how many connections an address holds
open, and how many requests it may make (:mod:`server.lobby`). Sans-I/O: time is an input.

- Who: the TCP peer, unless the peer is a configured trusted proxy (``--trusted-proxy``, an
  address or a network); then the ``X-Forwarded-For`` entries are read from the right, and the
  first one that is not itself a trusted proxy is the client (:func:`client_address`). A header
  from any other peer is ignored: anyone can write one.
- Connections: at most :data:`MAX_CONNECTIONS_PER_ADDRESS` open at once per TCP peer, and
  :data:`MAX_CONNECTIONS` over all of them (:class:`ConnectionCounts`). A trusted proxy's
  connections carry many clients: they count only against the total.
- Requests: a token bucket per client (:data:`ADDRESS_RATE_PER_S`, :data:`ADDRESS_BURST`),
  an IPv6 client counted by its /64 (one host is given a whole /64) (:class:`AddressBudgets`).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from haptic_collab.server.security import TokenBucket

#: Connections one address may hold open at once (each carries one request). Over it a new
#: connection is answered 503 with ``Retry-After`` (or cut off if it sends nothing).
MAX_CONNECTIONS_PER_ADDRESS = 16
#: Connections open at once, over every address.
MAX_CONNECTIONS = 256
#: Requests a second one client may make, sustained, and saved up.
ADDRESS_RATE_PER_S = 5.0
ADDRESS_BURST = 20.0
#: Clients whose request budgets are kept at most (full buckets are forgotten first).
MAX_ADDRESSES = 4096
#: Prefix length an IPv6 client is counted by [bits].
IPV6_BUDGET_PREFIX = 64

Network = ipaddress.IPv4Network | ipaddress.IPv6Network
Address = ipaddress.IPv4Address | ipaddress.IPv6Address


def _address(text: str) -> Address:
    """An IP address, an IPv4-mapped IPv6 one as IPv4. Raises ValueError when not one."""
    addr = ipaddress.ip_address(text.strip())
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        return addr.ipv4_mapped
    return addr


def parse_proxies(texts: Iterable[str]) -> tuple[Network, ...]:
    """The trusted proxies of ``--trusted-proxy`` values: addresses or networks.

    Parameters
    ----------
    texts : iterable of str
        Each an address (``10.0.0.7``, ``fd00::1``) or a network (``10.0.0.0/8``).

    Returns
    -------
    tuple of ipaddress networks

    Raises
    ------
    ValueError
        A value that is neither (host bits set in a network count as an error too).
    """
    out = []
    for text in texts:
        try:
            out.append(ipaddress.ip_network(text.strip()))
        except ValueError:
            raise ValueError(
                f"a trusted proxy is an address or a network such as 10.0.0.0/8, got {text!r}"
            ) from None
    return tuple(out)


def _trusted(addr: Address, proxies: Sequence[Network]) -> bool:
    return any(addr.version == net.version and addr in net for net in proxies)


def is_trusted(peer: str, proxies: Sequence[Network]) -> bool:
    """Whether the TCP peer ``peer`` is one of ``proxies`` (False for a peer that is no IP)."""
    try:
        return _trusted(_address(peer), proxies)
    except ValueError:
        return False


def client_address(peer: str, forwarded_for: Sequence[str], proxies: Sequence[Network]) -> str:
    """The address a request is from.

    Parameters
    ----------
    peer : str
        The TCP peer's address.
    forwarded_for : sequence of str
        The values of every ``X-Forwarded-For`` header of the request, in order (each a
        comma-separated list of addresses, the nearest proxy's last).
    proxies : sequence of networks
        The trusted proxies (:func:`parse_proxies`).

    Returns
    -------
    str
        ``peer`` when it is not a trusted proxy or sent no ``X-Forwarded-For``; else the
        rightmost entry that is not a trusted proxy (all of them trusted: the leftmost).

    Raises
    ------
    ValueError
        A trusted proxy sent an entry that is not an IP address.
    """
    if not proxies or not forwarded_for or not is_trusted(peer, proxies):
        return peer
    hops = [h.strip() for value in forwarded_for for h in value.split(",")]
    client = peer
    for hop in reversed(hops):
        try:
            addr = _address(hop)
        except ValueError:
            raise ValueError(
                f"X-Forwarded-For from a trusted proxy holds {hop[:64]!r}, not an IP address"
            ) from None
        client = str(addr)
        if not _trusted(addr, proxies):
            break
    return client


def budget_key(address: str) -> str:
    """What a client's request budget is kept under: its address, an IPv6 one's /64."""
    try:
        addr = _address(address)
    except ValueError:
        return address
    if isinstance(addr, ipaddress.IPv6Address):
        return str(ipaddress.IPv6Network((addr, IPV6_BUDGET_PREFIX), strict=False))
    return str(addr)


@dataclass
class ConnectionCounts:
    """Connections open at once, per address and in all.

    Parameters
    ----------
    per_address : int
        Most connections one address may hold (:data:`MAX_CONNECTIONS_PER_ADDRESS`), >= 1.
    total : int
        Most connections in all (:data:`MAX_CONNECTIONS`), >= 1.

    Raises
    ------
    ValueError
        A limit below 1.
    """

    per_address: int = MAX_CONNECTIONS_PER_ADDRESS
    total: int = MAX_CONNECTIONS
    open_by_address: dict[str, int] = field(default_factory=dict)
    open_total: int = 0

    def __post_init__(self) -> None:
        if self.per_address < 1 or self.total < 1:
            raise ValueError("connection limits are at least 1")

    def admit(self, address: str, *, proxy: bool = False) -> str | None:
        """Count a new connection from ``address``; ``proxy``: a trusted proxy's (no cap of
        its own).

        Returns
        -------
        str or None
            None: admitted and counted (call :meth:`release` when it closes); else why not
            (``"address"``: that address is at its cap, ``"total"``: the lobby is), and it is
            not counted.
        """
        if self.open_total >= self.total:
            return "total"
        held = self.open_by_address.get(address, 0)
        if not proxy and held >= self.per_address:
            return "address"
        self.open_by_address[address] = held + 1
        self.open_total += 1
        return None

    def release(self, address: str) -> None:
        """A connection :meth:`admit` counted has closed."""
        held = self.open_by_address.get(address, 0) - 1
        if held > 0:
            self.open_by_address[address] = held
        else:
            self.open_by_address.pop(address, None)
        self.open_total = max(0, self.open_total - 1)


@dataclass
class AddressBudgets:
    """A request budget per client: a token bucket each, time an input.

    Parameters
    ----------
    rate_per_s : float
        Requests a second one client may make, sustained (:data:`ADDRESS_RATE_PER_S`).
    burst : float
        Requests it may save up (:data:`ADDRESS_BURST`).
    max_addresses : int
        Clients kept at most (:data:`MAX_ADDRESSES`): when full, the ones whose buckets are
        full again are forgotten; if none is, a new client is refused.
    """

    rate_per_s: float = ADDRESS_RATE_PER_S
    burst: float = ADDRESS_BURST
    max_addresses: int = MAX_ADDRESSES
    buckets: dict[str, TokenBucket] = field(default_factory=dict)

    def spent(self, address: str, now_s: float) -> bool:
        """Whether ``address`` has less than one request left at ``now_s`` [s] (nothing is
        charged: a connection can be refused before its request is read)."""
        bucket = self.buckets.get(budget_key(address))
        return bucket is not None and bucket.refill(now_s) < 1.0

    def take(self, address: str, now_s: float) -> bool:
        """Charge one request to ``address`` at ``now_s`` [s]; False: over its budget."""
        key = budget_key(address)
        bucket = self.buckets.get(key)
        if bucket is None:
            if len(self.buckets) >= self.max_addresses:
                full = [k for k, b in self.buckets.items() if b.refill(now_s) >= b.burst]
                for k in full:
                    del self.buckets[k]
                if len(self.buckets) >= self.max_addresses:
                    return False
            bucket = self.buckets[key] = TokenBucket(self.rate_per_s, self.burst, now_s)
        return bucket.take(1.0, now_s)
