"""Sweep plots: the aggregation against hand-computed means (failed cells NaN, unsafe mask), and the PNGs."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.image import imread

from hil.sweep.plots import heatmap_grid, make_plots, metric_value, plot_file_name

LATENCIES = [0.0, 0.1, 0.5]
LOSSES = [0.0, 0.2]
LAWS = ["finite_time", "consensus"]


def metric(lat: float, p: float, law: str, seed: int) -> float:
    return 10 * lat + p + seed + (1.0 if law == "consensus" else 0.0)


def synthetic_rows() -> list[dict]:
    """results.csv-like rows (strings, as csv.DictReader gives them) over 3 x 2 x 2 laws x 2 seeds."""
    rows = []
    for lat in LATENCIES:
        for p in LOSSES:
            for law in LAWS:
                for seed in (0, 1):
                    rows.append({"radio.latency_s": str(lat), "radio.loss.p": str(p), "controller.law": law,
                                 "seed": str(seed), "coupler_max_abs_m": repr(metric(lat, p, law, seed)),
                                 "unsafe": "False", "error": ""})
    # one failed run at (lat 0.0, p 0.2): its cell must be NaN, not the mean of the other three
    failed = next(r for r in rows if r["radio.latency_s"] == "0.0" and r["radio.loss.p"] == "0.2")
    failed.update(coupler_max_abs_m="", error="RuntimeError: boom", unsafe="")
    # one unsafe run (one seed of one law) at (lat 0.5, p 0.0)
    next(r for r in rows if r["radio.latency_s"] == "0.5" and r["radio.loss.p"] == "0.0"
         and r["controller.law"] == "consensus" and r["seed"] == "1")["unsafe"] = "True"
    return rows


def test_heatmap_grid_means_over_seeds_and_other_axes():
    g = heatmap_grid(synthetic_rows(), "coupler_max_abs_m", "radio.latency_s", "radio.loss.p")
    assert g.x_values == LATENCIES and g.y_values == LOSSES
    # mean over law (+0, +1) and seed (0, 1): 10 lat + p + 1
    expected = np.array([[10 * lat + p + 1.0 for lat in LATENCIES] for p in LOSSES])
    expected[1, 0] = np.nan  # the failed run's cell
    np.testing.assert_allclose(g.values, expected, rtol=0, atol=1e-12)
    assert g.runs.tolist() == [[4, 4, 4], [4, 4, 4]]
    assert g.failed.tolist() == [[0, 0, 0], [1, 0, 0]]
    assert g.unsafe.tolist() == [[False, False, True], [False, False, False]]


def test_where_fixes_an_axis_and_numbers_match_strings():
    rows = synthetic_rows()
    for r in rows:  # a mix of numbers and strings must land in the same cells
        if r["seed"] == "1" and r["coupler_max_abs_m"]:
            r["radio.latency_s"] = float(r["radio.latency_s"])
            r["coupler_max_abs_m"] = float(r["coupler_max_abs_m"])
    g = heatmap_grid(rows, "coupler_max_abs_m", "radio.latency_s", "radio.loss.p", where={"controller.law": "consensus"})
    assert g.runs.tolist() == [[2, 2, 2], [2, 2, 2]]
    # consensus only: mean over seeds 0, 1 of 10 lat + p + seed + 1 = 10 lat + p + 1.5
    assert g.values[0, 1] == pytest.approx(10 * 0.1 + 0.0 + 1.5)
    assert g.values[1, 0] == pytest.approx(0.2 + 1.5)  # the failed run was finite_time: not in this slice
    assert g.unsafe.sum() == 1 and g.unsafe[0, 2]
    by_loss = heatmap_grid(rows, "coupler_max_abs_m", "radio.latency_s", "controller.law", where={"radio.loss.p": 0})
    assert by_loss.y_values == ["consensus", "finite_time"]  # text axes sort by text
    assert by_loss.values[1, 2] == pytest.approx(5.0 + 0.5)


def test_undefined_metric_is_nan_and_counted_apart_from_failures():
    rows = [{"x": "1", "y": "a", "settling_time_s": "12.5"}, {"x": "1", "y": "a", "settling_time_s": ""},
            {"x": "2", "y": "a", "settling_time_s": "20", "status": "ok"}]
    g = heatmap_grid(rows, "settling_time_s", "x", "y")
    assert math.isnan(g.values[0, 0]) and g.undefined[0, 0] == 1 and g.failed[0, 0] == 0
    assert g.values[0, 1] == 20.0
    single = heatmap_grid(rows, "settling_time_s", "x", None)  # a line without hue
    assert single.y_values == [""] and single.values[0, 1] == 20.0


def test_bad_plot_requests_are_named():
    rows = synthetic_rows()
    with pytest.raises(ValueError, match="no column 'gap_min_m'"):
        heatmap_grid(rows, "gap_min_m", "radio.latency_s", "radio.loss.p")
    with pytest.raises(ValueError, match="no run matches"):
        heatmap_grid(rows, "coupler_max_abs_m", "radio.latency_s", "radio.loss.p", where={"controller.law": "pid"})
    with pytest.raises(ValueError, match="'controller.law' is not numeric"):
        heatmap_grid(rows, "controller.law", "radio.latency_s", "radio.loss.p")
    assert math.isnan(metric_value("")) and metric_value("2.5") == 2.5 and metric_value(True) == 1.0


def red_pixels(path) -> int:
    img = imread(path)[..., :3]
    return int(np.count_nonzero((img[..., 0] > 0.8) & (img[..., 1] < 0.25) & (img[..., 2] < 0.25)))


def test_make_plots_writes_pngs_with_unsafe_marks(tmp_path):
    from hil.sweep.spec import PlotsConfig  # the sweep file's own plot schema (no `where`: duck typing copes)

    heat = {"metric": "coupler_max_abs_m", "x": "radio.latency_s", "y": "radio.loss.p"}
    line = {"metric": "coupler_max_abs_m", "x": "radio.latency_s", "hue": "controller.law"}
    spec = SimpleNamespace(plots=PlotsConfig(heatmaps=[heat], lines=[line]))
    paths = make_plots(spec, synthetic_rows(), tmp_path / "plots")
    assert [p.name for p in paths] == ["heatmap_coupler_max_abs_m__radio.loss.p_vs_radio.latency_s.png",
                                       "lines_coupler_max_abs_m__vs_radio.latency_s_by_controller.law.png"]
    safe_rows = [dict(r, unsafe="False") for r in synthetic_rows()]
    safe = make_plots(spec, safe_rows, tmp_path / "safe")
    for marked, clean in zip(paths, safe):
        assert marked.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and marked.stat().st_size > 10_000
        img = imread(marked)
        assert img.shape[0] > 300 and img.shape[1] > 400
        assert len(np.unique(img.reshape(-1, img.shape[-1]), axis=0)) > 50  # not a blank canvas
        assert red_pixels(marked) > red_pixels(clean) + 50  # the unsafe hatch / x / shading is drawn


def test_make_plots_accepts_plain_mappings_with_where(tmp_path):
    spec = {"plots": {"heatmaps": [{"metric": "coupler_max_abs_m", "x": "radio.latency_s", "y": "radio.loss.p",
                                    "where": {"controller.law": "consensus"}}] * 2,
                      "lines": [{"metric": "coupler_max_abs_m", "x": "controller.law", "hue": None}]}}
    paths = make_plots(spec, synthetic_rows(), tmp_path)
    assert [p.name for p in paths] == [
        "heatmap_coupler_max_abs_m__radio.loss.p_vs_radio.latency_s__controller.law=consensus.png",
        "heatmap_coupler_max_abs_m__radio.loss.p_vs_radio.latency_s__controller.law=consensus_2.png",
        "lines_coupler_max_abs_m__vs_controller.law.png",
    ]
    assert all(p.stat().st_size > 10_000 for p in paths)
    assert make_plots(SimpleNamespace(plots=None), synthetic_rows(), tmp_path / "none") == []
    assert plot_file_name("lines", "gap min/m", "a b", None, {"k": 0.50}) == "lines_gap_min_m__vs_a_b__k=0.5.png"
