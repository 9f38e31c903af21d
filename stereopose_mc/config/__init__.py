"""Scenario files: pydantic models, YAML loading with line numbers, SI conversion."""

from .loader import ScenarioError, load_scenario, load_scenario_text
from .schema import Scenario

__all__ = ["Scenario", "ScenarioError", "load_scenario", "load_scenario_text"]
