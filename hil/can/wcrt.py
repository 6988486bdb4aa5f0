"""Worst-case response-time analysis of CAN messages (Davis, Burns, Bril, Lukkien 2007, section 5).

The revised exact analysis for fixed-priority non-preemptive CAN arbitration: blocking by one
lower-priority frame, a priority-level busy period that may hold several instances of the message,
and the response time of every instance in it. The emulator's measured latencies are checked
against these bounds. All arithmetic is exact, in integer nanoseconds.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from fractions import Fraction

from hil.can.frame import (
    EXT_ID_LIMIT,
    MAX_FD_DATA_BYTES,
    STD_ID_LIMIT,
    best_case_fd_frame_bits,
    bit_time_ns,
    worst_case_fd_frame_bits,
    worst_case_frame_bits,
)

_NS_PER_S = 1_000_000_000
_MAX_ITERATIONS = 1_000_000  # a fixed point below utilisation 1 is reached long before this


@dataclass(frozen=True)
class BusRates:
    """A bus's bit timing as the analysis needs it: the nominal bitrate and, for CAN FD, the data-phase one."""

    nominal: int
    data: int | None = None  # CAN FD with BRS: the data phase's bitrate (default: the nominal one)
    fd: bool = False
    brs: bool = True

    def __post_init__(self) -> None:
        bit_time_ns(self.nominal)
        if self.data is not None:
            bit_time_ns(self.data)
            if not self.fd:
                raise ValueError("a data bitrate is for CAN FD (fd=True)")
            if self.data < self.nominal:
                raise ValueError(f"data bitrate {self.data} is below the nominal bitrate {self.nominal}")

    @property
    def tau_ns(self) -> int:
        """The nominal bit time (the queueing resolution of arbitration)."""
        return bit_time_ns(self.nominal)

    def worst_case_bits(self, dlc: int, extended: bool) -> tuple[int, int]:
        """(bits at the nominal rate, bits at the data rate) of the longest frame of ``dlc`` data bytes."""
        if not self.fd:
            return worst_case_frame_bits(dlc, extended), 0
        return worst_case_fd_frame_bits(dlc, extended, self.brs)

    def best_case_ns(self, dlc: int, extended: bool) -> int:
        """The shortest transmission of a frame of ``dlc`` data bytes (no stuff bits), incl. the intermission."""
        if not self.fd:
            return ((54 if extended else 34) + 8 * dlc + 13) * self.tau_ns
        nominal, data = best_case_fd_frame_bits(dlc, extended, self.brs)
        return nominal * self.tau_ns + data * bit_time_ns(self.data or self.nominal)

    def worst_case_ns(self, dlc: int, extended: bool) -> int:
        """The longest transmission of a frame of ``dlc`` data bytes, incl. the intermission."""
        nominal, data = self.worst_case_bits(dlc, extended)
        return nominal * self.tau_ns + data * bit_time_ns(self.data or self.nominal)

    def __str__(self) -> str:
        if not self.fd:
            return f"{self.nominal / 1000:g} kbit/s"
        data = f", data phase {(self.data or self.nominal) / 1e6:g} Mbit/s" if self.brs else ", no bit-rate switch"
        return f"{self.nominal / 1000:g} kbit/s CAN FD{data}"


def as_rates(bitrate: "int | BusRates") -> BusRates:
    """A classical bus's bitrate, or the rates of any bus, as ``BusRates``."""
    return bitrate if isinstance(bitrate, BusRates) else BusRates(bitrate)


@dataclass(frozen=True)
class CanMessage:
    """A periodic CAN message: lower can_id = higher priority; deadline defaults to the period."""

    name: str
    can_id: int
    period_s: float
    dlc: int
    extended: bool = False
    jitter_s: float = 0.0
    deadline_s: float | None = None

    def __post_init__(self) -> None:
        limit = EXT_ID_LIMIT if self.extended else STD_ID_LIMIT
        if not _is_int(self.can_id) or not 0 <= self.can_id < limit:
            raise ValueError(f"message {self.name!r}: can_id={self.can_id!r} out of range 0..{limit - 1:#x}")
        if not _is_int(self.dlc) or not 0 <= self.dlc <= MAX_FD_DATA_BYTES:
            raise ValueError(f"message {self.name!r}: dlc={self.dlc!r} out of range 0..{MAX_FD_DATA_BYTES} (data bytes)")
        _check_time(self.name, "period_s", self.period_s, positive=True)
        _check_time(self.name, "jitter_s", self.jitter_s, positive=False)
        if self.deadline_s is not None:
            _check_time(self.name, "deadline_s", self.deadline_s, positive=True)

    @property
    def deadline(self) -> float:
        """Relative deadline in seconds (the period unless given)."""
        return self.period_s if self.deadline_s is None else self.deadline_s


@dataclass(frozen=True)
class WcrtResult:
    """Analysis result of one message; r_s is inf when its priority level is overloaded."""

    c_s: float  # worst-case transmission time (worst-case stuffed frame incl. IFS)
    r_s: float  # worst-case response time: queued (incl. its jitter) .. end of transmission
    schedulable: bool  # r_s <= deadline
    utilisation_hp: float  # utilisation of the strictly higher-priority messages
    utilisation_hep: float  # ... plus the message itself (>= 1 means no bound)
    blocking_s: float  # B_m: longest lower-priority frame
    busy_period_s: float  # t_m: priority-level busy period (inf if unbounded)
    instances: int  # Q_m: instances of the message in the busy period (0 if unbounded)
    critical_instance: int  # the q in 0..Q_m-1 with the largest response time (-1 if unbounded)


def _is_int(value: object) -> bool:
    """True for ints and numpy integers, False for bool, float and the rest."""
    if isinstance(value, bool):
        return False
    try:
        operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        return False
    return True


def _check_time(name: str, field: str, value: float, positive: bool) -> None:
    """Raise ValueError naming the message and field if a time is not finite and in range."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (positive and round(value * _NS_PER_S) <= 0):
        need = "> 0 (at least 1 ns)" if positive else ">= 0"
        raise ValueError(f"message {name!r}: {field}={value!r} must be a finite number {need}")


def _ns(seconds: float) -> int:
    """Seconds to whole nanoseconds (the analysis runs in exact integer arithmetic)."""
    return round(seconds * _NS_PER_S)


def _ceil_div(a: int, b: int) -> int:
    """ceil(a / b) for integers, b > 0."""
    return -(-a // b)


def _fixed_point(f: Callable[[int], int], start: int) -> int:
    """Least fixed point of a monotone f at or above `start` (start must not exceed it)."""
    x = start
    for _ in range(_MAX_ITERATIONS):
        nxt = f(x)
        if nxt == x:
            return x
        x = nxt
    raise RuntimeError(f"fixed-point iteration did not converge from {start} ns")


def _check_unique(messages: Sequence[CanMessage]) -> None:
    """Names and identifiers must be unique (arbitration compares can_id alone)."""
    by_id: dict[int, str] = {}
    names: set[str] = set()
    for m in messages:
        if m.name in names:
            raise ValueError(f"duplicate message name {m.name!r}")
        names.add(m.name)
        if m.can_id in by_id:
            raise ValueError(f"messages {by_id[m.can_id]!r} and {m.name!r} share can_id={m.can_id:#x}")
        by_id[m.can_id] = m.name


def _instance_response(
    q: int, b: int, c: int, t: int, j: int, hp: list[tuple[int, int, int]], tau: int, w0: int
) -> tuple[int, int]:
    """(w_m(q), R_m(q)) in ns: eq. w = B + qC + sum_hp ceil((w + J_k + tau)/T_k) C_k; R = J + w - qT + C."""

    def queuing(w: int) -> int:
        return b + q * c + sum(_ceil_div(w + jk + tau, tk) * ck for ck, tk, jk in hp)

    w = _fixed_point(queuing, max(w0, b + q * c))
    return w, j + w - q * t + c


def _worst_instance(
    b: int, own: tuple[int, int, int], hp: list[tuple[int, int, int]], tau: int
) -> tuple[int, int, int, int]:
    """(busy period t_m, instances Q_m, max_q R_m(q), that q) in ns; own and hp are (C, T, J)."""
    c, t, j = own
    hep = hp + [own]
    busy = _fixed_point(lambda x: b + sum(_ceil_div(x + jk, tk) * ck for ck, tk, jk in hep), c)
    n_inst = _ceil_div(busy + j, t)
    r_max, q_max, w = -1, -1, 0
    for q in range(n_inst):
        w, r = _instance_response(q, b, c, t, j, hp, tau, w)
        if r > r_max:
            r_max, q_max = r, q
    return busy, n_inst, r_max, q_max


def response_times(
    messages: list[CanMessage], bitrate: int | BusRates, error_overhead: None = None
) -> dict[str, WcrtResult]:
    """Worst-case response time of every message on an error-free bus, keyed by message name.

    Blocking is the longest lower-priority frame (the paper's B_m = max over lp(m) of C_k; the
    paper's simpler sufficient test, blocking by the longest frame on the bus, is not used).
    """
    if error_overhead is not None:
        raise NotImplementedError(f"error_overhead={error_overhead!r}: only an error-free bus (None) is modelled")
    rates = as_rates(bitrate)
    tau = rates.tau_ns
    _check_unique(messages)
    order = sorted(messages, key=lambda m: m.can_id)
    cs = [_worst_ns(rates, m) for m in order]
    ts = [_ns(m.period_s) for m in order]
    js = [_ns(m.jitter_s) for m in order]
    results: dict[str, WcrtResult] = {}
    u_hp = Fraction(0)
    for i, m in enumerate(order):
        c, t, j = cs[i], ts[i], js[i]
        b = max(cs[i + 1 :], default=0)
        u_hep = u_hp + Fraction(c, t)
        if u_hep >= 1:
            results[m.name] = WcrtResult(
                c / _NS_PER_S, math.inf, False, float(u_hp), float(u_hep), b / _NS_PER_S, math.inf, 0, -1
            )
        else:
            busy, n_inst, r_max, q_max = _worst_instance(b, (c, t, j), list(zip(cs[:i], ts[:i], js[:i])), tau)
            results[m.name] = WcrtResult(
                c / _NS_PER_S,
                r_max / _NS_PER_S,
                r_max <= _ns(m.deadline),
                float(u_hp),
                float(u_hep),
                b / _NS_PER_S,
                busy / _NS_PER_S,
                n_inst,
                q_max,
            )
        u_hp = u_hep
    return results


def bus_utilisation(messages: list[CanMessage], bitrate: int | BusRates) -> float:
    """Sum of C_k / T_k with worst-case frame lengths."""
    rates = as_rates(bitrate)
    return float(sum(Fraction(_worst_ns(rates, m), _ns(m.period_s)) for m in messages))


def _worst_ns(rates: BusRates, m: CanMessage) -> int:
    """C_m: the longest transmission of message m, or ValueError naming it (a length its format lacks)."""
    try:
        return rates.worst_case_ns(m.dlc, m.extended)
    except ValueError as exc:
        raise ValueError(f"message {m.name!r}: {exc}") from None
