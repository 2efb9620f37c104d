"""The lobby's limits per client, without sockets (server/lobby_limits.py, server/lobby_peers.py).

Who a request is from when proxies stand in front, how many connections one address may hold,
a request budget per client, and which replica owns a name: what an operator configures and
relies on, checked as plain functions with time as an input.
"""

from __future__ import annotations

import pytest

from haptic_collab.server.lobby_limits import (
    AddressBudgets,
    ConnectionCounts,
    budget_key,
    client_address,
    parse_proxies,
)
from haptic_collab.server.lobby_peers import Peers, check_peer_request, sign_peer_request

PROXIES = parse_proxies(["10.0.0.0/8", "fd00::/8", "192.0.2.7"])


def test_x_forwarded_for_counts_only_from_a_trusted_proxy() -> None:
    # a client straight to the lobby cannot pick its address by writing the header
    assert client_address("203.0.113.9", ["198.51.100.1"], PROXIES) == "203.0.113.9"
    # through one proxy: the address it saw
    assert client_address("10.1.2.3", ["198.51.100.1"], PROXIES) == "198.51.100.1"
    # a client's own entries are left of the proxies': the rightmost untrusted one counts
    assert client_address("10.1.2.3", ["6.6.6.6, 198.51.100.1, 10.9.9.9"], PROXIES) == (
        "198.51.100.1"
    )
    # several headers are one list, in order
    assert client_address("192.0.2.7", ["6.6.6.6", "198.51.100.2"], PROXIES) == "198.51.100.2"
    # IPv6 and an IPv4-mapped peer
    assert client_address("fd00::5", ["2001:db8::1"], PROXIES) == "2001:db8::1"
    assert client_address("::ffff:10.0.0.1", ["198.51.100.3"], PROXIES) == "198.51.100.3"
    # a proxy that sends no header (a health check) is itself the client
    assert client_address("10.1.2.3", [], PROXIES) == "10.1.2.3"
    # no proxies configured: the header never counts
    assert client_address("10.1.2.3", ["198.51.100.1"], ()) == "10.1.2.3"


def test_a_bad_forwarded_entry_or_proxy_setting_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="X-Forwarded-For .* 'unknown', not an IP address"):
        client_address("10.1.2.3", ["unknown"], PROXIES)
    with pytest.raises(ValueError, match="address or a network such as 10.0.0.0/8"):
        parse_proxies(["10.0.0.1/8"])  # host bits set
    with pytest.raises(ValueError, match="got 'lb.example'"):
        parse_proxies(["lb.example"])


def test_one_address_holds_at_most_its_share_of_connections() -> None:
    counts = ConnectionCounts(per_address=3, total=5)
    assert [counts.admit("a") for _ in range(4)] == [None, None, None, "address"]
    assert counts.admit("b") is None
    assert counts.admit("proxy", proxy=True) is None  # a proxy has no cap of its own
    assert counts.admit("c") == "total"
    counts.release("a")
    assert counts.admit("c") is None
    with pytest.raises(ValueError):
        ConnectionCounts(per_address=0)


def test_a_request_budget_per_client_and_per_ipv6_64() -> None:
    budgets = AddressBudgets(rate_per_s=5.0, burst=20.0, max_addresses=2)
    assert sum(budgets.take("198.51.100.1", 0.0) for _ in range(30)) == 20
    assert budgets.take("198.51.100.2", 0.0)  # another client is not charged
    # at most max_addresses kept: a new client is refused until one is full again
    assert not budgets.take("198.51.100.3", 0.0)
    assert budgets.take("198.51.100.1", 1.0)  # 5 more a second
    assert budgets.take("198.51.100.3", 1.0)  # 198.51.100.2's bucket is full: forgotten
    # one host is handed a /64: its addresses share one budget
    assert budget_key("2001:db8:1:2::1") == budget_key("2001:db8:1:2:ffff::9")
    assert budget_key("2001:db8:1:3::1") != budget_key("2001:db8:1:2::1")


def test_each_name_has_one_owner_and_a_peer_request_is_signed() -> None:
    urls = ["http://lobby-0:8780", "http://lobby-1:8780", "http://lobby-2:8780"]
    a = Peers.of(urls, urls[0])
    b = Peers.of(list(reversed(urls)), urls[1])  # the order of the list does not matter
    owners = {n: a.owner(n) for n in (f"room-{i}" for i in range(300))}
    assert all(b.owner(n) == o for n, o in owners.items())
    assert {urls[i]: list(owners.values()).count(urls[i]) for i in range(3)} == pytest.approx(
        {u: 100 for u in urls}, abs=35
    )
    # a replica dropped from the list moves only its own names
    two = Peers.of(urls[:2], urls[0])
    assert all(two.owner(n) == o for n, o in owners.items() if o != urls[2])
    with pytest.raises(ValueError, match="not among its peers"):
        Peers.of(urls, "http://lobby-9:8780")
    with pytest.raises(ValueError, match="listed twice"):
        Peers.of([urls[0], urls[0] + "/"], urls[0])
    secret = b"s" * 32
    sig = sign_peer_request(secret, "anatomy", 1_000_030)
    assert check_peer_request(secret, "anatomy", sig, 1_000_000.0)
    assert not check_peer_request(secret, "other-room", sig, 1_000_000.0)
    assert not check_peer_request(b"t" * 32, "anatomy", sig, 1_000_000.0)
    assert not check_peer_request(secret, "anatomy", sig, 1_000_031.0)  # expired
    assert not check_peer_request(secret, "anatomy", "garbage", 1_000_000.0)
