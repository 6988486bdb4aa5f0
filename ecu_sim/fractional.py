"""Riemann-Liouville fractional integral of a sampled signal, with bounded memory (seed 004's D^{-r}).

    I^r f(t) = 1/Gamma(r) int_0^t (t - tau)^(r-1) f(tau) dtau,      0 < r < 1

f is known at t_j = j h (one sample per control cycle) and taken piecewise linear between samples
(product-trapezoidal rule: exact for piecewise-linear f, error O(h^2) for smooth f, O(h^(1+p)) for
f ~ t^p near 0). A plain Grunwald-Letnikov sum is only O(h) and needs the whole history; this one
splits the kernel at a lag of L steps:

- local part, lags 0..L h: the exact kernel integrals against the linear pieces (L + 1 weights);
- history, lags >= L h: the kernel is replaced by a sum of exponentials,
  t^(r-1)/Gamma(r) ~= sum_k w_k exp(-s_k t) on [L h, T_max], from the trapezoidal rule in y = ln s of
  t^(r-1)/Gamma(r) = sin(pi r)/pi int exp((1-r) y - e^y t) dy. Each exponential mode k keeps one number
  H_k = int exp(-s_k (t - tau)) f(tau) dtau over the history, updated exactly each step for linear f.

Memory is bounded: L + 1 samples and K modes (K ~ 200 for tol = 1e-10, T_max = 1e5 s), whatever the run
length; each update costs O(L + K). The kernel approximation's relative error on [L h, T_max] is
measured at construction (``kernel_error``) and is below ``tol``; beyond T_max (default ~28 h of one
run) it degrades gracefully (the slowest modes stop resolving the kernel's tail).
"""
from __future__ import annotations

import math

import numpy as np


def _local_weights(r: float, window: int) -> np.ndarray:
    """(window, window + 1): row n-1 holds the weights on f_n, f_{n-1}, ..., of the first n intervals.

    Interval k (lags sigma in [k-1, k], in steps) contributes (k P - Q) f_{n-k+1} + (Q - (k-1) P) f_{n-k}
    with P = int sigma^(r-1), Q = int sigma^r over it (times h^r / Gamma(r), applied by the caller).
    """
    rows = np.zeros((window, window + 1))
    for n in range(1, window + 1):
        for k in range(1, n + 1):
            p = (k**r - (k - 1) ** r) / r
            q = (k ** (r + 1) - (k - 1) ** (r + 1)) / (r + 1)
            rows[n - 1, k - 1] += k * p - q
            rows[n - 1, k] += q - (k - 1) * p
    return rows


def kernel_modes(r: float, t_min: float, t_max: float, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(w, s): sum_k w_k exp(-s_k t) ~= t^(r-1)/Gamma(r) for t in [t_min, t_max], relative error ~ tol."""
    c = math.sin(math.pi * r) / math.pi
    # left end: the neglected tail c e^{(1-r) y_lo}/(1-r) stays below tol times the kernel at t_max
    y_lo = (math.log(tol * (1 - r) / c) + (r - 1) * math.log(t_max) - math.lgamma(r)) / (1 - r)
    # right end: exp(-e^y t_min) below ~tol e^-10 beyond it
    y_hi = math.log((10.0 - math.log(tol)) / t_min)
    hy = math.pi**2 / (12.0 - math.log(tol))  # trapezoid error ~ exp(-pi^2 / hy) (analytic in |Im y| < pi/2)
    y = np.arange(y_lo, y_hi + hy, hy)
    return c * hy * np.exp((1.0 - r) * y), np.exp(y)


def _interval_moments(s: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """I0 = int_0^h e^{-s v} dv and I1 = (1/h) int_0^h v e^{-s v} dv, accurate for every s h."""
    x = s * h
    i0 = -np.expm1(-x) / s
    small = x < 1e-2
    i1 = np.empty_like(x)
    xs = x[small]  # series h sum_j (-x)^j / (j! (j + 2))
    i1[small] = h * (0.5 - xs / 3 + xs**2 / 8 - xs**3 / 30 + xs**4 / 144 - xs**5 / 840)
    xl, sl = x[~small], s[~small]
    i1[~small] = (i0[~small] - h * np.exp(-xl)) / (sl * h)
    return i0, i1


class FractionalIntegral:
    """I^r f at the sample times t_j = j h of f; call :meth:`update` once per sample (the first at t = 0).

    ``channels`` > 1 integrates that many signals at once (one call, same cost): pass a sequence and get
    an array back (a view, overwritten by the next call).
    """

    def __init__(self, order: float, step: float, window: int = 16, t_max: float = 1e5, tol: float = 1e-10,
                 channels: int = 1) -> None:
        if not 0.0 < order < 1.0:
            raise ValueError(f"fractional order r = {order!r} must lie in (0, 1)")
        if not (step > 0 and math.isfinite(step)):
            raise ValueError(f"step = {step!r} s must be a positive number")
        if window < 1 or t_max <= window * step or not 0 < tol < 1e-3 or channels < 1:
            raise ValueError(f"need window >= 1, t_max > window * step, 0 < tol < 1e-3 and channels >= 1 "
                             f"(got {window}, {t_max}, {tol}, {channels})")
        self.order, self.step, self.window, self.channels = order, step, window, channels
        self._local = _local_weights(order, window) * (step**order / math.gamma(order))
        self._w, s = kernel_modes(order, window * step, t_max, tol)
        self._decay = np.exp(-s * step)[:, None]
        i0, i1 = _interval_moments(s, step)
        lag = np.exp(-s * window * step)
        self._ab = np.stack([lag * (i0 - i1), lag * i1], axis=1)  # (K, 2): weights on the interval's newer / older sample
        self.kernel_error = self._measure_kernel_error(s, t_max)
        # ring buffer of the last L + 1 samples (f_{n-j} in slot (n - j) mod (L + 1)); _rot[m - 1, pos] holds the
        # local weights of the first m intervals laid out by slot when f_n sits in slot pos
        self._ring = np.zeros((window + 1, channels))
        lag = np.arange(window + 1)
        self._rot = np.zeros((window, window + 1, window + 1))
        for pos in range(window + 1):
            self._rot[:, pos, (pos - lag) % (window + 1)] = self._local
        self._hist = np.zeros((len(s), channels))
        self._tmp = np.empty((len(s), channels))
        self._out = np.zeros(channels)
        self._pair = np.empty((2, channels))
        self._n = 0

    @property
    def memory(self) -> int:
        """Floats of state kept per channel: samples in the local window plus exponential modes (independent of t)."""
        return self._ring.shape[0] + self._hist.shape[0]

    def _measure_kernel_error(self, s: np.ndarray, t_max: float) -> float:
        t = np.geomspace(self.window * self.step, t_max, 400)
        approx = np.exp(-np.outer(t, s)) @ self._w
        exact = t ** (self.order - 1) / math.gamma(self.order)
        return float(np.max(np.abs(approx / exact - 1.0)))

    def reset(self) -> None:
        """Forget the history (the next sample is t = 0 again)."""
        self._ring.fill(0.0)
        self._hist.fill(0.0)
        self._n = 0

    def update(self, f):
        """Take f(t_n) (n = number of earlier samples) and return I^r f (t_n): a float, or an array per channel."""
        n, ring, L, out = self._n, self._ring, self.window, self._out
        pos = n % (L + 1)  # ring slot of f_n; it held f_{n-L-1}
        if n > L:  # the interval [t_{n-L-1}, t_{n-L}] leaves the local window for the history
            pair = self._pair
            pair[0] = ring[(n - L) % (L + 1)]  # f_{n-L}, the interval's newer end
            pair[1] = ring[pos]  # f_{n-L-1}
            np.matmul(self._ab, pair, out=self._tmp)
            np.multiply(self._hist, self._decay, out=self._hist)
            np.add(self._hist, self._tmp, out=self._hist)
        ring[pos] = f
        self._n = n + 1
        if n == 0:
            out.fill(0.0)
        else:
            np.dot(self._rot[min(n, L) - 1, pos], ring, out=out)
            if n > L:
                out += self._w @ self._hist
        return float(out[0]) if self.channels == 1 else out
