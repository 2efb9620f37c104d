"""The demo's port check matches what the server does, and a wildcard bind prints reachable URLs."""

from __future__ import annotations

import asyncio
import socket
import sys

import pytest

from haptic_collab import demo as haptic_demo
from haptic_collab.demo import _port_free
from haptic_collab.server.urls import reachable_addresses, viewer_urls


def _leave_time_wait() -> int:
    """A loopback port whose last connection lingers in TIME_WAIT (as after a demo run)."""
    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        port = int(listener.getsockname()[1])
        client = socket.create_connection(("127.0.0.1", port))
        conn, _ = listener.accept()
        conn.close()  # the server side closes first: its end stays in TIME_WAIT for a minute
        client.close()
    return port


@pytest.mark.skipif(sys.platform != "linux", reason="TIME_WAIT bind rules are Linux's")
def test_a_port_in_time_wait_is_free_for_the_server_and_for_the_check() -> None:
    port = _leave_time_wait()
    with socket.socket() as plain, pytest.raises(OSError):
        plain.bind(("127.0.0.1", port))  # what the old check did: "port ... is in use"
    assert _port_free("127.0.0.1", port)

    async def serve() -> None:  # what the server does (asyncio sets SO_REUSEADDR on POSIX)
        server = await asyncio.start_server(lambda r, w: None, "127.0.0.1", port)
        server.close()
        await server.wait_closed()

    asyncio.run(serve())


def test_a_port_someone_listens_on_is_in_use() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        assert not _port_free("127.0.0.1", int(busy.getsockname()[1]))


def test_the_demo_refuses_a_busy_port_with_one_clear_message() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = int(busy.getsockname()[1])
        with pytest.raises(ValueError, match=f"port {port} on 127.0.0.1 is in use"):
            haptic_demo.run_demo(haptic_demo.DemoOptions(port=port, headless=True))


def test_a_wildcard_bind_lists_loopback_and_the_machines_addresses() -> None:
    urls = viewer_urls("0.0.0.0", 8765)
    assert urls[0] == "http://127.0.0.1:8765/"
    assert not any("0.0.0.0" in u for u in urls)
    assert len(urls) == len(set(urls))
    for ip in reachable_addresses("0.0.0.0")[1:]:
        socket.inet_aton(ip)  # IPv4 addresses only for an IPv4 wildcard
        assert not ip.startswith(("127.", "169.254.", "0."))
    # the host's own name resolves to one of the listed addresses, unless it is loopback-only
    try:
        own = {str(i[4][0]) for i in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)}
    except OSError:
        own = set()
    lan = {ip for ip in own if not ip.startswith("127.")}
    assert lan <= set(reachable_addresses("0.0.0.0"))
    v6 = viewer_urls("::", 80)
    assert v6[0] == "http://[::1]:80/" and "http://127.0.0.1:80/" in v6
    assert not any("[::]" in u for u in v6)


def test_a_specific_host_is_printed_as_given() -> None:
    assert viewer_urls("127.0.0.1", 8765) == ["http://127.0.0.1:8765/"]
    assert viewer_urls("10.1.2.3", 80) == ["http://10.1.2.3:80/"]
    assert viewer_urls("::1", 80) == ["http://[::1]:80/"]
