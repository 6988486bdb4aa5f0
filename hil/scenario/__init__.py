"""Scenario files: schema (model.py) and loading with clear errors (loader.py)."""
from hil.scenario.loader import ScenarioError, load_scenario, packaged_scenarios, resolve, scenario_from_dict
from hil.scenario.model import Scenario

__all__ = ["Scenario", "ScenarioError", "load_scenario", "packaged_scenarios", "resolve", "scenario_from_dict"]
