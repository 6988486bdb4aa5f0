"""Sweeps: a grid of scenario variants run in parallel (local processes or Dask), one results table, plots."""
from hil.sweep.results import load_results
from hil.sweep.runner import SweepResult, run_sweep
from hil.sweep.spec import GridPoint, SweepError, SweepSpec, load_sweep, packaged_sweeps

__all__ = ["GridPoint", "SweepError", "SweepResult", "SweepSpec", "load_results", "load_sweep", "packaged_sweeps", "run_sweep"]
