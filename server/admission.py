"""Admission and flood control of one room: who may connect, and the frame and byte budgets of
every connection and every source address (DESIGN section 7b: no connection, however hostile,
may cost other users their patch rate).

Sans-I/O like the room (:mod:`server.room`): times are passed in, nothing reads a clock. The room
asks :meth:`FloodControl.connect` before it registers a connection, charges every arriving frame
with :meth:`FloodControl.charge` and :meth:`FloodControl.charge_address`, credits the budgets for
its own stalls with :meth:`FloodControl.credit_stall`, and closes what they name.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol, TypeVar

from haptic_collab.server.security import TokenBucket
from haptic_collab.shared.protocol import MAX_CLIENT_FRAME_BYTES

__all__ = ["Budgeted", "FloodControl", "Refusal", "RoomLimits"]


@dataclass(frozen=True)
class RoomLimits:
    """Abuse limits per connection and per source address.

    Attributes
    ----------
    max_users : int
        Haptic users in the room at once.
    max_viewers : int
        Viewers at once.
    max_pending : int
        Connections that have not sent ``hello`` yet, in total. When full, a newcomer from an
        address with fewer pending connections evicts the oldest pending connection of the
        address that holds the most.
    max_pending_per_address : int
        Connections from one source address that have not sent ``hello`` yet.
    hello_timeout_s : float
        A connection that has not sent ``hello`` within this [s] is closed.
    max_connections : int
        Users, viewers and pending connections together.
    max_connections_per_address : int
        Connections from one source address (a NAT may hide a lab behind one).
    rate_per_s, burst : float
        Token bucket on incoming frames of one connection: sustained frames/s and burst size.
    bytes_per_s, bytes_burst : float
        Token bucket on incoming bytes of one connection [bytes/s, bytes].
    address_rate_per_s, address_burst : float
        Frames/s and burst of all connections from one source address together.
    address_bytes_per_s, address_bytes_burst : float
        Bytes/s and burst of all connections from one source address together.
    stall_credit_max_s : float
        The longest time [s] the server may have been behind its schedule that is credited to
        the budgets (:meth:`FloodControl.credit_stall`): no budget then holds more than ``burst +
        rate * stall_credit_max_s``.
    stall_credit_keep_s : float
        How long [s] the credit for a stall is kept after it, at least (as long as the stall
        lasted, when longer), for the backlog to be read; then it lapses.
    stale_after_s : float
        A user whose last state is older than this [s] no longer loads the object.
    max_errors : int
        Non-fatal errors on one connection before it is closed.
    clamp_report_interval_s : float
        At most one ``force_clamped`` error per user per this interval [s] (clamps are all
        counted, see :meth:`server.room.Room.force_clamps`).
    """

    max_users: int = 32
    max_viewers: int = 64
    max_pending: int = 32
    max_pending_per_address: int = 8
    hello_timeout_s: float = 5.0
    max_connections: int = 128
    max_connections_per_address: int = 64
    rate_per_s: float = 400.0
    burst: float = 400.0
    bytes_per_s: float = 64 * 1024
    bytes_burst: float = 64 * 1024
    address_rate_per_s: float = 2000.0
    address_burst: float = 2000.0
    address_bytes_per_s: float = 1024 * 1024
    address_bytes_burst: float = 1024 * 1024
    stall_credit_max_s: float = 30.0
    stall_credit_keep_s: float = 2.0
    stale_after_s: float = 0.5
    max_errors: int = 50
    clamp_report_interval_s: float = 1.0


class Budgeted(Protocol):
    """What flood control reads of a connection (the room's connection record)."""

    @property
    def address(self) -> str:
        """Source address of the connection."""
        ...

    @property
    def connected_at_s(self) -> float:
        """When it connected [s]."""
        ...

    @property
    def hello(self) -> object | None:
        """Its ``hello``; None while it is pending."""
        ...

    @property
    def frames(self) -> TokenBucket:
        """Its own frame budget."""
        ...

    @property
    def bytes(self) -> TokenBucket:
        """Its own byte budget."""
        ...


C = TypeVar("C", bound=Budgeted)


@dataclass(frozen=True)
class Refusal:
    """Why a connection or a frame is refused: the ``error`` code and message (fatal)."""

    code: str
    message: str


@dataclass
class _Address:
    """Budgets shared by every connection from one source address."""

    frames: TokenBucket
    bytes: TokenBucket


class FloodControl:
    """The budgets of one room's connections and source addresses.

    Parameters
    ----------
    limits : RoomLimits
        The abuse limits.
    sim_period_s : float
        The room's simulation period N*T [s]: lateness below it is jitter, not a stall
        (:meth:`credit_stall`).
    """

    def __init__(self, limits: RoomLimits, sim_period_s: float) -> None:
        self.limits = limits
        self.sim_period_s = float(sim_period_s)
        self._addresses: dict[str, _Address] = {}
        #: Up to when [s] the budgets have been credited for the server being behind schedule.
        self._credited_to_s = -math.inf

    def connect(self, conns: Iterable[C], address: str) -> Refusal | C | None:
        """May a new connection from ``address`` join the room holding ``conns``?

        A :class:`Refusal` when the room holds ``max_connections``, when ``address`` holds
        ``max_connections_per_address`` or ``max_pending_per_address`` connections, or when
        ``max_pending`` connections wait in total and no address holds more of them than
        ``address`` does. Otherwise, with the pending total full, the connection to evict to
        make room (the oldest pending one of the address holding the most); else None.
        """
        lim = self.limits
        every = list(conns)
        if len(every) >= lim.max_connections:
            return Refusal("room_full", "too many connections")
        same = [c for c in every if c.address == address]
        if len(same) >= lim.max_connections_per_address:
            return Refusal(
                "too_many_connections",
                f"at most {lim.max_connections_per_address} connections per address",
            )
        if sum(1 for c in same if c.hello is None) >= lim.max_pending_per_address:
            return Refusal(
                "too_many_pending",
                f"at most {lim.max_pending_per_address} connections per address may wait for hello",
            )
        pending: dict[str, list[C]] = {}
        for c in every:
            if c.hello is None:
                pending.setdefault(c.address, []).append(c)
        if sum(len(v) for v in pending.values()) >= lim.max_pending:
            heavy = max(pending.values(), key=len)
            if len(heavy) <= len(pending.get(address, [])) + 1:
                return Refusal("too_many_pending", "too many connections wait for hello")
            return min(heavy, key=lambda c: c.connected_at_s)
        return None

    def open(self, address: str, now_s: float) -> tuple[TokenBucket, TokenBucket]:
        """The budgets (frames, bytes) of a new connection from ``address`` at ``now_s`` [s];
        the address's shared budgets are opened if it has none."""
        lim = self.limits
        if address not in self._addresses:
            self._addresses[address] = _Address(
                TokenBucket(lim.address_rate_per_s, lim.address_burst, now_s),
                TokenBucket(lim.address_bytes_per_s, lim.address_bytes_burst, now_s),
            )
        return (
            TokenBucket(lim.rate_per_s, lim.burst, now_s),
            TokenBucket(lim.bytes_per_s, lim.bytes_burst, now_s),
        )

    @staticmethod
    def charge(conn: Budgeted, size: int, now_s: float) -> Refusal | None:
        """Charge one frame of ``size`` bytes to the connection's own budgets at ``now_s`` [s].

        A :class:`Refusal` (``rate_limited`` or ``frame_too_large``) when its frame rate, the
        frame size limit or its byte rate is exceeded, checked in that order; else None.
        """
        if not conn.frames.take(1.0, now_s):
            return Refusal("rate_limited", "too many messages; slow down to the simulation rate")
        if size > MAX_CLIENT_FRAME_BYTES:
            return Refusal(
                "frame_too_large", f"frames are limited to {MAX_CLIENT_FRAME_BYTES} bytes"
            )
        if not conn.bytes.take(size, now_s):
            return Refusal("rate_limited", "too many bytes; slow down")
        return None

    def charge_address(self, conn: C, conns: Iterable[C], size: int, now_s: float) -> C | None:
        """Charge one frame of ``size`` bytes to the connection's source address.

        When the address has spent its budget, returns its heaviest connection among ``conns``
        (the one that spent the largest share of its own budget), to be closed with
        ``rate_limited``; the frame at hand is still admitted when it came from another, lighter
        connection. None when the address is within its budget.
        """
        addr = self._addresses.get(conn.address)
        if addr is None:  # pragma: no cover - opened with the connection
            return None
        if addr.frames.take(1.0, now_s) & addr.bytes.take(size, now_s):
            return None
        same = [c for c in conns if c.address == conn.address]
        addr.frames.level -= 1.0
        addr.bytes.level -= size
        return min(same, key=lambda c: min(c.frames.fill, c.bytes.fill))

    def credit_stall(self, conns: Iterable[Budgeted], due_s: float, now_s: float) -> None:
        """The simulation tick due at ``due_s`` [s] has not run by ``now_s`` [s]: credit budgets.

        The budgets are charged when the server reads a frame. While the server is behind its
        own schedule (its event loop blocked, or waiting for a CPU on a busy machine) it reads
        nothing, and everything the clients sent meanwhile arrives at once when it resumes. A
        bucket that was full at the start of such a stall would have refilled no further, so a
        client sending steadily below its rate (a state twice per tick) reads as a flood once the
        stall holds back more than a burst of its frames or bytes, and was closed with
        ``rate_limited``: punished for the server's stall. So every budget (per connection and
        per address, frames and bytes) is refilled over the stall *without* its burst cap
        (:meth:`TokenBucket.lift`): the backlog is charged as if it had been read on time.

        Why this and not another fix:

        - It is exact where it matters and changes nothing elsewhere. A bucket that was being
          spent during the stall (a flooder) gains exactly the refill it always gets: it is
          still cut off when it sends faster than ``rate`` (``lift`` never credits a stretch
          twice). Only a bucket that would have hit its cap gains more, and by no more than
          ``rate`` times the stall: over any stretch of time that contains the stall a client
          is admitted at most ``burst + rate * stretch``, as on a server that never stalls.
        - The credit is bounded: it covers at most ``stall_credit_max_s`` of a stall and lapses
          ``stall_credit_keep_s`` after the stall (or as long as the stall lasted, when longer),
          so a quiet connection cannot save it up for later.
        - The room stays sans-I/O: the I/O layer says when the tick was due and what time it is
          now (it knows its schedule); the room reads no clock. A server that keeps its schedule
          never falls a period behind, so a flood there is cut off exactly as before.
        - Dropping superseded ``state`` frames uncounted (latest wins at the input as at the
          output) would leave a ``state`` flood unbudgeted, although parsing every frame is
          exactly what a flood costs the server, and would not help ``ping`` or byte budgets.

        Lateness below one simulation period is jitter, not a stall, and is not credited;
        credits are given in steps of at least one period (each step touches every budget).
        """
        period = self.sim_period_s
        start = max(due_s, self._credited_to_s)
        if now_s - due_s < period or now_s - start < period:
            return
        lim = self.limits
        keep_until_s = now_s + max(lim.stall_credit_keep_s, now_s - due_s)
        buckets = [b for c in conns for b in (c.frames, c.bytes)]
        buckets += [b for a in self._addresses.values() for b in (a.frames, a.bytes)]
        for bucket in buckets:
            bucket.lift(start, now_s, keep_until_s, lim.stall_credit_max_s)
        self._credited_to_s = now_s

    def forget_idle(self, conns: Iterable[Budgeted], now_s: float) -> None:
        """Drop the budgets of addresses with no connection once they have refilled."""
        live = {c.address for c in conns}
        for address in [a for a in self._addresses if a not in live]:
            budget = self._addresses[address]
            if budget.frames.refill(now_s) >= budget.frames.burst and (
                budget.bytes.refill(now_s) >= budget.bytes.burst
            ):
                del self._addresses[address]
