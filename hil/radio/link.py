"""One direction of the train-to-train radio: range, tunnels, rate cap, loss and latency per frame.

``RadioLink.offer`` decides, one frame at a time, whether and when a frame handed to the radio
arrives. Times are integer nanoseconds (the virtual-time kernel's clock).

Choices made here (and relied on by the tests):

* Checks run in order range -> blackout -> injected fault (``impairment``, hil/faults/radio.py: its drops
  count as ``fault``, its delay adds to the latency) -> rate cap -> loss; the first that fails names the
  drop in ``stats``. A position of ``None`` means "not known yet" and never causes a drop.
* Rate cap: a token bucket with burst 1 and one token every ``round(1e9 / rate_cap_hz)`` ns;
  a frame passes iff at least one period has elapsed since the last frame that took a token.
  Frames dropped by range or blackout take no token; frames later lost on the air do.
* Common random numbers: every offered frame consumes exactly one Gilbert-Elliott transition
  draw, one loss draw and one jitter draw, whatever happens to it. Frame k of a run therefore
  sees the same random numbers whatever the range, loss probability or jitter size, so sweeps
  compare configurations on the same randomness. Draws come in blocks of ``BLOCK`` frames.
* Gilbert-Elliott: the chain starts in a state drawn from its stationary distribution and is
  stepped once per offered frame (before that frame's loss draw, in the new state).
* No reordering: a radio delivers the frames of one direction in the order they were sent, so a
  frame is delivered no earlier than the previous delivered frame of the same link (it waits
  behind it, as in a FIFO modem queue). Equal delivery times keep the offer order if the
  scheduler is FIFO among equal times.
"""
from __future__ import annotations

import numpy as np

from hil.scenario.model import RadioConfig

BLOCK = 1024  # frames' worth of random numbers drawn per refill
STAT_KEYS = ("offered", "delivered", "out_of_range", "blackout", "lost", "rate_capped")


def _stationary_bad(p_gb: float, p_bg: float) -> float:
    """Stationary probability of the bad state, pi_bad = p_gb / (p_gb + p_bg) (0 if the chain never moves)."""
    total = p_gb + p_bg
    return p_gb / total if total > 0 else 0.0


class RadioLink:
    """One direction (sender -> receiver) of a train-to-train radio link."""

    def __init__(self, cfg: RadioConfig, rng: np.random.Generator, name: str) -> None:
        self.name = name
        self.cfg = cfg
        self.stats: dict[str, int] = dict.fromkeys(STAT_KEYS, 0)
        self._rng = rng
        self._range_m = cfg.range_m
        self._blackouts = self._check_blackouts(cfg)
        self._latency_ns = int(round(cfg.latency_s * 1e9))
        self._jitter_ns = cfg.jitter_s * 1e9
        self._period_ns = None if cfg.rate_cap_hz is None else int(round(1e9 / cfg.rate_cap_hz))
        loss = cfg.loss
        self._loss_model = loss.model
        self._p = loss.p
        self._p_gb, self._p_bg = loss.p_good_to_bad, loss.p_bad_to_good
        self._loss_good, self._loss_bad = loss.loss_good, loss.loss_bad
        self._bad = bool(rng.random() < _stationary_bad(self._p_gb, self._p_bg))
        self._next_token_ns: int | None = None  # None: bucket full since the start
        self._last_offer_ns: int | None = None
        self._last_delivery_ns = -(2**62)
        self._k = BLOCK  # index into the current block; BLOCK forces a refill on first use
        self._u_step: list[float] = []
        self._u_loss: list[float] = []
        self._jit: list[int] = []
        self.impairment = None  # hil.faults.radio.RadioImpairment: t_ns -> extra delay (ns), or None to drop

    # ---- what another implementation of the link (the engine's radio.rs) needs to continue this one exactly
    @property
    def latency_ns(self) -> int:
        """The fixed latency of every delivery (ns)."""
        return self._latency_ns

    @property
    def period_ns(self) -> int | None:
        """The rate cap's minimum spacing between deliveries (ns), or None without a cap."""
        return self._period_ns

    @property
    def starts_bad(self) -> bool:
        """Whether the Gilbert-Elliott loss chain starts in its bad state (drawn at construction)."""
        return self._bad

    def next_draws(self) -> tuple[list[float], list[float], list[int]]:
        """The next block of per-frame draws from this link's numpy stream: (state step, loss, jitter ns), as the
        link itself would use them."""
        self._refill()
        return self._u_step, self._u_loss, self._jit

    def _check_blackouts(self, cfg: RadioConfig) -> tuple[tuple[float, float], ...]:
        for k, b in enumerate(cfg.blackouts):
            if not b.end_m > b.start_m:
                raise ValueError(
                    f"radio link {self.name}: radio.blackouts[{k}] end_m ({b.end_m}) must be after start_m ({b.start_m})"
                )
        return tuple((b.start_m, b.end_m) for b in cfg.blackouts)

    def _refill(self) -> None:
        """Draw the next BLOCK frames' transition, loss and jitter numbers in three rng calls."""
        rng = self._rng
        u = rng.random((2, BLOCK))
        dist = self.cfg.jitter_distribution
        if dist == "uniform":
            z = rng.random(BLOCK)
        elif dist == "normal":
            z = np.maximum(rng.standard_normal(BLOCK), 0.0)
        else:
            z = rng.standard_exponential(BLOCK)
        self._u_step = u[0].tolist()
        self._u_loss = u[1].tolist()
        self._jit = np.rint(z * self._jitter_ns).astype(np.int64).tolist()
        self._k = 0

    def _in_blackout(self, pos: float | None) -> bool:
        if pos is None:
            return False
        for start, end in self._blackouts:
            if start <= pos < end:
                return True
        return False

    def _lost(self, u_step: float, u_loss: float) -> bool:
        """Step the loss model once and say whether this frame is lost."""
        model = self._loss_model
        if model == "none":
            return False
        if model == "bernoulli":
            return u_loss < self._p
        if self._bad:
            if u_step < self._p_bg:
                self._bad = False
        elif u_step < self._p_gb:
            self._bad = True
        return u_loss < (self._loss_bad if self._bad else self._loss_good)

    def _take_token(self, t_ns: int) -> bool:
        period = self._period_ns
        if period is None:
            return True
        if self._next_token_ns is not None and t_ns < self._next_token_ns:
            return False
        self._next_token_ns = t_ns + period
        return True

    def offer(self, t_ns: int, sender_pos_m: float | None, receiver_pos_m: float | None) -> int | None:
        """Delivery time (int ns) of a frame handed to the radio at ``t_ns``, or None if it is dropped."""
        if self._last_offer_ns is not None and t_ns < self._last_offer_ns:
            raise ValueError(f"radio link {self.name}: offer at t_ns={t_ns} is earlier than the previous offer at {self._last_offer_ns}")
        self._last_offer_ns = t_ns
        stats = self.stats
        stats["offered"] += 1
        if self._k == BLOCK:
            self._refill()
        k = self._k
        self._k = k + 1
        lost = self._lost(self._u_step[k], self._u_loss[k])  # stepped for every offered frame
        if sender_pos_m is not None and receiver_pos_m is not None and abs(sender_pos_m - receiver_pos_m) > self._range_m:
            stats["out_of_range"] += 1
            return None
        if self._blackouts and (self._in_blackout(sender_pos_m) or self._in_blackout(receiver_pos_m)):
            stats["blackout"] += 1
            return None
        extra = 0
        if self.impairment is not None:  # an injected fault (after range and tunnels: they are the physics)
            extra = self.impairment(t_ns)
            if extra is None:
                stats["fault"] = stats.get("fault", 0) + 1
                return None
        if not self._take_token(t_ns):
            stats["rate_capped"] += 1
            return None
        if lost:
            stats["lost"] += 1
            return None
        deliver = t_ns + self._latency_ns + self._jit[k] + extra
        if deliver < self._last_delivery_ns:
            deliver = self._last_delivery_ns  # no overtaking within one direction
        self._last_delivery_ns = deliver
        stats["delivered"] += 1
        return deliver


def loss_rate_expected(cfg: RadioConfig) -> float:
    """Long-run loss probability of the configured loss model (pi_good*loss_good + pi_bad*loss_bad for GE)."""
    loss = cfg.loss
    if loss.model == "none":
        return 0.0
    if loss.model == "bernoulli":
        return loss.p
    pi_bad = _stationary_bad(loss.p_good_to_bad, loss.p_bad_to_good)
    return (1.0 - pi_bad) * loss.loss_good + pi_bad * loss.loss_bad


__all__ = ["BLOCK", "STAT_KEYS", "RadioLink", "loss_rate_expected"]
