"""The two rates of the multirate loop, declared once: servo rate 1/T and simulation rate 1/(N*T).

The paper (section 2) runs the local model at the servo period T and the object at N*T; the
lifted loop (eq. 3-5) exists only for a whole N. :class:`Rates` holds both rates, checks that N
is whole, and gives T, N*T and N to everything that needs them (the server's room and object,
the client's session, the stability and gain-design code), so no one recomputes them.

Pure: no sockets, threads or clocks. Units: rates [Hz], periods [s].
"""

from __future__ import annotations

from dataclasses import dataclass, field

from haptic_collab.shared.checks import positive as _positive

#: Relative tolerance within which two periods [s] (or a ratio and a whole number) count as equal.
PERIOD_RTOL = 1e-9


def dividing_rates(servo_rate_hz: float, lo_hz: float = 5.0, hi_hz: float = 500.0) -> list[float]:
    """Simulation rates in ``[lo_hz, hi_hz]`` [Hz] of which ``servo_rate_hz`` is a whole multiple
    (the rates :class:`Rates` accepts), ascending; for messages that suggest a valid rate.

    Raises
    ------
    ValueError
        ``servo_rate_hz`` not a finite number > 0.
    """
    servo = _positive("servo rate", servo_rate_hz)
    n_max = int(servo // lo_hz) if lo_hz > 0 else 0
    rates = {servo / n for n in range(1, n_max + 1) if lo_hz <= servo / n <= hi_hz}
    return sorted(r for r in rates if abs(r - round(r)) < 1e-9)


@dataclass(frozen=True)
class Rates:
    """Servo rate 1/T and simulation rate 1/(N*T) [Hz], with N = servo rate / simulation rate whole.

    Parameters
    ----------
    servo_rate_hz : float
        1/T [Hz], the haptic (fast) loop: finite, > 0.
    sim_rate_hz : float
        1/(N*T) [Hz], the object simulation (slow) loop: finite, > 0.

    Attributes
    ----------
    ratio : int
        N >= 1, servo ticks per simulation tick.

    Raises
    ------
    ValueError
        A rate that is not a finite number > 0, or a servo rate that is not a whole multiple
        (>= 1) of the simulation rate; the message lists the simulation rates in [5, 500] Hz
        that do divide the servo rate.
    """

    servo_rate_hz: float
    sim_rate_hz: float
    ratio: int = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        servo = _positive("servo rate", self.servo_rate_hz)
        sim = _positive("simulation rate", self.sim_rate_hz)
        object.__setattr__(self, "servo_rate_hz", servo)
        object.__setattr__(self, "sim_rate_hz", sim)
        q = servo / sim
        n = round(q)
        if n < 1 or abs(q - n) > PERIOD_RTOL * max(1.0, q):
            ok = dividing_rates(servo)
            listing = f"; rates that divide {servo:g} Hz: {', '.join(f'{r:g}' for r in ok)} Hz"
            raise ValueError(
                f"servo rate {servo:g} Hz must be a whole multiple of the simulation rate "
                f"{sim:g} Hz (N = {q:.3g}){listing if ok else ''}"
            )
        object.__setattr__(self, "ratio", int(n))

    @property
    def servo_period_s(self) -> float:
        """T = 1 / servo rate [s]."""
        return 1.0 / self.servo_rate_hz

    @property
    def sim_period_s(self) -> float:
        """N*T [s], computed as 1 / simulation rate (the value the object steps with)."""
        return 1.0 / self.sim_rate_hz

    def check_sim_period(self, sim_period_s: float, what: str) -> None:
        """Refuse a simulation period [s] declared elsewhere that is not this one's N*T.

        Parameters
        ----------
        sim_period_s : float
            The other period [s].
        what : str
            Who declared it, for the message (e.g. ``"the object"``).

        Raises
        ------
        ValueError
            The periods differ by more than :data:`PERIOD_RTOL` (relative), or ``sim_period_s`` is
            not a finite number > 0.
        """
        other = _positive(f"{what}'s simulation period", sim_period_s)
        mine = self.sim_period_s
        if abs(other - mine) > PERIOD_RTOL * max(other, mine):
            raise ValueError(
                f"{what} steps every {other * 1e3:g} ms ({1.0 / other:g} Hz) but the rates say "
                f"{mine * 1e3:g} ms ({self.sim_rate_hz:g} Hz): build both from one Rates"
            )


def rate_ratio(servo_rate_hz: float, sim_rate_hz: float) -> int:
    """N, the number of servo ticks per simulation tick: ``Rates(servo, sim).ratio``.

    Raises
    ------
    ValueError
        As :class:`Rates`: a rate not positive and finite, or the servo rate not a whole multiple
        (>= 1) of the simulation rate.
    """
    return Rates(servo_rate_hz, sim_rate_hz).ratio
