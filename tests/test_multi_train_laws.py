"""Seed 002's potential law and its two comparison laws, seed 003's observers: signs, zeros, weights, feed-forward."""
from __future__ import annotations

import math

import pytest

from ecu_sim.controllers.base import build_controller
from ecu_sim.controllers.potential import potential_force
from ecu_sim.controllers.safe_range import wall_force
from ecu_sim.observers import Eso
from ecu_sim.view import AgentInfo, LocalView, NeighbourView, ReferenceView
from hil.runtime.firmware import plant_info
from hil.scenario import load_scenario
from hil.scenario.model import TrackConfig

SC = load_scenario("seed002")
INFO = plant_info(SC)
L, LS = 200.0, 7200.0  # train length, l_s: d_r = 7.4 km head to head


def agent(train: int) -> AgentInfo:
    return AgentInfo(train=train, unit=0, n_trains=5, n_units=1, mass_kg=400e3, length_m=L,
                     offset_m=train * (L + LS), has_reference=True)


def view(train: int, x: float, v: float, ahead: tuple[float, float] | None, behind: tuple[float, float] | None,
         v_r: float = 65.0) -> LocalView:
    nbrs = []
    if ahead:
        nbrs.append(NeighbourView("inter", "ahead", (train - 1) * (L + LS), x=ahead[0], v=ahead[1], age_s=0.0, valid=True))
    if behind:
        nbrs.append(NeighbourView("inter", "behind", (train + 1) * (L + LS), x=behind[0], v=behind[1], age_s=0.0, valid=True))
    return LocalView(t=1.0, dt=0.05, x=x, v=v, neighbours=nbrs, ref=ReferenceView(x=0.0, v=v_r, a=0.0, age_s=0.0, valid=True))


def accel(law: str, v: LocalView, train: int = 2, **params) -> float:
    c = build_controller(law, params, agent(train), INFO)
    return c.step(v).accel_mps2 - INFO.resistance_per_kg(v.v)


def test_potential_is_zero_at_d_r_attractive_above_repulsive_below():
    for a in (0.5, 1.0, 3.0, 5.0):
        assert potential_force(0.0, a, 3000.0) == 0.0
        assert potential_force(3000.0, a, 3000.0) == pytest.approx(1.0)  # F_p(+-L) = +-1 for every a
        assert potential_force(-3000.0, a, 3000.0) == pytest.approx(-1.0)
        assert potential_force(100.0, a, 3000.0) > 0 > potential_force(-100.0, a, 3000.0)
        assert potential_force(-250.0, a, 3000.0) == -potential_force(250.0, a, 3000.0)
    # with this reading of (4) a larger a is weaker below the 3 km scale (documented in the law's module)
    assert potential_force(500.0, 1.0, 3000.0) > potential_force(500.0, 3.0, 3000.0) > potential_force(500.0, 5.0, 3000.0)


@pytest.mark.parametrize("law,params", [("potential", {"tuning": "fixed", "a_fixed": 3.0}), ("potential", {}),
                                        ("fixed_spacing", {}), ("safe_range", {})])
def test_pair_force_signs(law, params):
    """Gap ahead too long: the follower speeds up; gap behind too long: the train waits. At d_r and v_r: nothing."""
    x = 50000.0
    at_rest = view(2, x, 65.0, (x + 7400.0, 65.0), (x - 7400.0, 65.0))
    assert accel(law, at_rest, **params) == pytest.approx(0.0, abs=1e-12)
    long_ahead = view(2, x, 65.0, (x + 7400.0 + 2000.0, 65.0), (x - 7400.0, 65.0))
    long_behind = view(2, x, 65.0, (x + 7400.0, 65.0), (x - 7400.0 - 2000.0, 65.0))
    short_ahead = view(2, x, 65.0, (x + 7400.0 - 500.0, 65.0), (x - 7400.0, 65.0))
    assert accel(law, long_ahead, **params) > 0 > accel(law, long_behind, **params)
    if law != "safe_range":  # the safe range has no force for gaps a little above d_r, but it pushes back below it
        assert accel(law, short_ahead, **params) < 0
    else:
        assert accel(law, short_ahead, **params) < 0 and accel(law, view(2, x, 65.0, (x + 7400.0 + 1000.0, 65.0), None), **params) == 0


def test_speed_consensus_sign_is_stable():
    """(6) printed with +sum(v_i - v_j) is unstable; ours pulls a slow train up towards its neighbours and v_r."""
    x = 50000.0
    slow = view(2, x, 60.0, (x + 7400.0, 65.0), (x - 7400.0, 65.0))
    fast = view(2, x, 70.0, (x + 7400.0, 65.0), (x - 7400.0, 65.0))
    assert accel("potential", slow) == pytest.approx(0.05 * (5.0 + 5.0 + 5.0))
    assert accel("potential", fast) == pytest.approx(-0.05 * 15.0)


def test_fuzzy_weight_follows_the_rule_table():
    c = build_controller("potential", {}, agent(2), INFO)
    assert c.weight(0.0, 0.0) == pytest.approx(3.0)  # NB, NB -> ZO -> a = 3
    assert c.weight(3000.0, 0.0) == pytest.approx(1.0 + 4.0 / 18.0)  # PB, NB -> NB (edge triangle centroid)
    assert c.weight(0.0, 10.0) > c.weight(0.0, 0.0)  # a reference step asks for a larger weight
    fixed = build_controller("potential", {"tuning": "fixed", "a_fixed": 5.0}, agent(2), INFO)
    assert fixed.weight(1234.0, 1.0) == 5.0


def test_feed_forward_cancels_grade_and_curve_from_the_line_map():
    c = build_controller("potential", {"line_map": SC.track.model_dump()}, agent(2), INFO)
    flat = build_controller("potential", {}, agent(2), INFO)
    on_grade = 70000.0  # seed002's 5 permille grade
    v = view(2, on_grade, 65.0, (on_grade + 7400.0, 65.0), (on_grade - 7400.0, 65.0))
    diff = c.step(v).accel_mps2 - flat.step(v).accel_mps2
    assert diff == pytest.approx(9.81 * 5.0 / 1000.0)
    assert TrackConfig(**SC.controller.params["line_map"]) == SC.track  # the packaged firmware map is the track


def test_wall_force_is_flat_inside_the_safe_range():
    assert wall_force(0.0, 1500.0, 1e-3) == 0.0 and wall_force(1499.0, 1500.0, 1e-3) == 0.0
    assert wall_force(2000.0, 1500.0, 1e-3) == pytest.approx(0.5)
    assert wall_force(-100.0, 1500.0, 1e-3) == pytest.approx(-0.1)


def test_eso_finds_a_constant_disturbance():
    """dz/dt = w + d with d = 0.3: the observer's estimate converges to d within a few 1/omega."""
    eso, z, dt = Eso(1.0), 0.0, 0.01
    for k in range(2000):
        w = math.sin(0.01 * k)
        eso.update(z, w, dt)
        z += dt * (w + 0.3)
    assert eso.d == pytest.approx(0.3, abs=1e-3) and abs(eso.rate) < 1e-3
    with pytest.raises(ValueError, match="omega"):
        Eso(0.0)


def test_seed002_variants_differ_only_where_they_should():
    base = SC.model_dump()
    for name, law in (("seed002-fixed-a1", "potential"), ("seed002-fixed-a3", "potential"), ("seed002-fixed-a5", "potential"),
                      ("seed002-bai", "fixed_spacing"), ("seed002-lyg", "safe_range"), ("seed002-limits", "potential")):
        other = load_scenario(name).model_dump()
        assert other["controller"]["law"] == law
        assert other["controller"]["params"]["line_map"] == base["controller"]["params"]["line_map"]
        for section in ("trains", "track", "reference", "ecu", "can", "radio", "duration_s"):
            assert other[section] == base[section], (name, section)
        limits_on = other["plant"].pop("limits")["enabled"]
        assert limits_on == (name == "seed002-limits")
        base_plant = dict(base["plant"])
        base_plant.pop("limits")
        assert other["plant"] == base_plant, name
