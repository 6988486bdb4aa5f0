"""Seed 002's fuzzy tuner (ecu_sim/fuzzy.py) against scikit-fuzzy and against an independent brute-force computation."""
from __future__ import annotations

import numpy as np
import pytest

from ecu_sim.fuzzy import LEVELS, SEED002_RULES, Mamdani2, centroid, rule_indices

CENTRES = [k / 6 for k in range(7)]


def brute_force(x1: float, x2: float, n: int = 60001) -> float:
    """Written independently of the firmware: per-rule loops, membership by explicit cases, a fine Riemann sum."""
    def mu(x: float, c: float) -> float:
        if abs(x - c) >= 1 / 6:
            return 0.0
        return 1 - abs(x - c) * 6

    x1, x2 = min(max(x1, 0.0), 1.0), min(max(x2, 0.0), 1.0)
    y = np.linspace(0.0, 1.0, n)
    out_sets = [np.clip(1 - np.abs(y - c) * 6, 0, None) for c in CENTRES]
    agg = np.zeros(n)
    for i, row in enumerate(SEED002_RULES):
        for j, name in enumerate(row):
            w = min(mu(x1, CENTRES[i]), mu(x2, CENTRES[j]))
            if w > 0:
                agg = np.maximum(agg, np.minimum(w, out_sets[LEVELS.index(name)]))
    return float(np.sum(y * agg) / np.sum(agg))


SAMPLES = [(0.0, 0.0), (1.0, 1.0), (0.03, 0.0), (0.2, 0.0), (0.5, 0.5), (0.9, 0.1), (1 / 6, 2 / 6), (1.3, -0.2)]
SAMPLES += [tuple(p) for p in np.random.default_rng(7).random((12, 2))]


@pytest.mark.parametrize("x1,x2", SAMPLES)
def test_matches_brute_force(x1, x2):
    assert Mamdani2()(x1, x2) == pytest.approx(brute_force(x1, x2), abs=1e-5)


def test_matches_scikit_fuzzy():
    fuzz = pytest.importorskip("skfuzzy")
    u = np.linspace(0, 1, 20001)
    mfs = [fuzz.trimf(u, [c - 1 / 6, c, c + 1 / 6]) for c in CENTRES]

    def sk(x1, x2):
        agg = np.zeros_like(u)
        for i in range(7):
            for j in range(7):
                w = min(fuzz.interp_membership(u, mfs[i], x1), fuzz.interp_membership(u, mfs[j], x2))
                agg = np.fmax(agg, np.fmin(w, mfs[LEVELS.index(SEED002_RULES[i][j])]))
        return fuzz.defuzz(u, agg, "centroid")

    m = Mamdani2()
    for x1, x2 in SAMPLES:
        if 0 <= x1 <= 1 and 0 <= x2 <= 1:
            assert m(x1, x2) == pytest.approx(sk(x1, x2), abs=1e-4)  # skfuzzy samples the universe


def test_rule_table_shapes_the_output():
    m = Mamdani2()
    # at a level centre only one rule fires: the output is that level's clipped-triangle centroid
    assert m(0.0, 0.0) == pytest.approx(0.5)  # NB, NB -> ZO
    assert m(1.0, 0.0) == pytest.approx(1 / 18)  # PB, NB -> NB (half triangle at the edge)
    # with |dv_r/dt| = 0, at the spacing levels' centres the weight falls as the spacing error grows (column NB
    # of Table 1: ZO NS NS NM NM NB NB); between centres Mamdani's centroid need not be monotone
    out = [m(c, 0.0) for c in CENTRES]
    assert all(b <= a + 1e-12 for a, b in zip(out, out[1:])) and out[0] > out[-1]
    # a faster reference change asks for a larger weight (each row of Table 1 rises to the right)
    assert m(0.2, 0.0) < m(0.2, 0.5) < m(0.2, 1.0)


def test_bad_tables_and_strengths_are_errors():
    with pytest.raises(ValueError, match="unknown level"):
        rule_indices(tuple(tuple("XX" for _ in range(7)) for _ in range(7)))
    with pytest.raises(ValueError, match="7 x 7"):
        rule_indices((("ZO",),))
    with pytest.raises(ValueError, match="not all zero"):
        centroid([0.0] * 7)
