"""The discrete Riemann-Liouville integral (ecu_sim/fractional.py) against closed forms and a full-memory sum.

Independent reference: I^r t^p = Gamma(p+1) / Gamma(p+1+r) t^(p+r).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from ecu_sim.fractional import FractionalIntegral

R = 4.0 / 9.0  # seed 004's order


def integrate(f, r: float, h: float, t_end: float, **kw) -> tuple[np.ndarray, np.ndarray, FractionalIntegral]:
    fi = FractionalIntegral(r, h, **kw)
    t = np.arange(int(round(t_end / h)) + 1) * h
    return t, np.array([fi.update(float(f(tj))) for tj in t]), fi


def closed_form(p: float, r: float, t: np.ndarray) -> np.ndarray:
    return math.gamma(p + 1) / math.gamma(p + 1 + r) * t ** (p + r)


@pytest.mark.parametrize("p", [0.0, 1.0])
@pytest.mark.parametrize("r", [R, 0.2, 0.8])
def test_piecewise_linear_inputs_are_integrated_to_roundoff_over_a_long_history(p: float, r: float) -> None:
    # product trapezoid is exact for linear f; what remains is the exponential-sum kernel (tol 1e-10)
    t, out, fi = integrate(lambda s: s**p, r, 0.01, 150.0)
    exact = closed_form(p, r, t[1:])
    assert np.max(np.abs(out[1:] / exact - 1.0)) < 1e-9
    assert fi.kernel_error < 1e-9


@pytest.mark.parametrize("p", [2.0, 3.0])
def test_smooth_inputs_converge_at_second_order(p: float) -> None:
    errors = []
    for h in (0.02, 0.01, 0.005):
        t, out, _ = integrate(lambda s: s**p, R, h, 20.0)
        late = t >= 1.0
        errors.append(np.max(np.abs(out[late] / closed_form(p, R, t[late]) - 1.0)))
    assert errors[-1] < 5e-5  # relative, from t = 1 s on
    for coarse, fine in zip(errors, errors[1:]):
        assert 3.5 < coarse / fine < 4.5  # halving the step divides the error by 4


def test_sqrt_input_converges_with_its_singular_start() -> None:
    errs = []
    for h in (0.01, 0.005):
        t, out, _ = integrate(np.sqrt, R, h, 10.0)
        errs.append(abs(out[-1] / closed_form(0.5, R, t[-1]) - 1.0))
    assert errs[1] < errs[0] < 1e-5


def test_matches_a_full_memory_product_trapezoid_sum_on_a_rough_signal() -> None:
    # the bounded-memory history (exponential modes) against the plain O(n^2) sum of the same rule
    rng = np.random.default_rng(1)
    h, n, r = 0.01, 2500, R
    f = np.cumsum(rng.normal(size=n + 1)) * 0.1 + np.sign(np.sin(np.arange(n + 1) * 0.05))
    fi = FractionalIntegral(r, h, window=8)
    ours = np.array([fi.update(x) for x in f])
    k = np.arange(1, n + 1)
    p_ = (k**r - (k - 1) ** r) / r
    q_ = (k ** (r + 1) - (k - 1) ** (r + 1)) / (r + 1)
    hi, lo = k * p_ - q_, q_ - (k - 1) * p_  # weights on f_{m-k+1} and f_{m-k}
    scale = h**r / math.gamma(r)
    for m in (1, 5, 8, 9, 10, 100, 1234, n):
        direct = scale * (np.dot(hi[:m], f[m - np.arange(1, m + 1) + 1]) + np.dot(lo[:m], f[m - np.arange(1, m + 1)]))
        assert ours[m] == pytest.approx(direct, rel=1e-9, abs=1e-9)


def test_memory_is_bounded_whatever_the_run_length() -> None:
    fi = FractionalIntegral(R, 0.0002)
    size = fi.memory
    for _ in range(20_000):
        fi.update(1.0)
    assert fi.memory == size < 300
    assert fi._hist.shape[0] + fi._ring.shape[0] == size


def test_channels_integrate_independently_and_reset_restarts() -> None:
    two = FractionalIntegral(R, 0.01, channels=2)
    a, b = FractionalIntegral(R, 0.01), FractionalIntegral(R, 0.01)
    for j in range(300):
        x, y = math.sin(0.1 * j), 0.01 * j
        out = two.update(np.array([x, y]))
        assert out[0] == pytest.approx(a.update(x), rel=1e-12, abs=1e-15)
        assert out[1] == pytest.approx(b.update(y), rel=1e-12, abs=1e-15)
    a.reset()
    assert a.update(5.0) == 0.0  # t = 0 again
    assert a.update(5.0) == pytest.approx(5.0 * closed_form(0.0, R, np.array(0.01)), rel=1e-12)


@pytest.mark.parametrize("kw, match", [({"order": 1.0}, "order"), ({"order": 0.0}, "order"), ({"step": -1.0}, "step"),
                                       ({"step": math.nan}, "step"), ({"window": 0}, "window")])
def test_bad_arguments_are_named(kw: dict, match: str) -> None:
    args = {"order": R, "step": 0.01} | kw
    with pytest.raises(ValueError, match=match):
        FractionalIntegral(**args)
