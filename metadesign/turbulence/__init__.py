"""Stage 5: modified von Karman screens, Rytov path model, point-source split-step propagation, the
scenario recipe and its validation against theory (:mod:`.validate`), and one beacon sample through a
device to the sensor (:class:`.chain.BeaconChain`)."""

from .chain import BeaconChain, BeaconSample
from .path import PathModel, SamplingReport, Scenario, check_sampling, solve_path
from .propagate import Turbulence, point_source, split_step, split_step_torch
from .scenario import load_scenario, scenario_from_dict
from .screens import ScreenGrid, psd_mvk, screens, structure_function_theory
from .validate import validate

__all__ = ["PathModel", "SamplingReport", "Scenario", "check_sampling", "solve_path", "Turbulence", "point_source",
           "split_step", "split_step_torch", "ScreenGrid", "psd_mvk", "screens", "structure_function_theory",
           "BeaconChain", "BeaconSample", "load_scenario", "scenario_from_dict", "validate"]
