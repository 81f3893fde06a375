"""Stage 5: modified von Karman screens, Rytov path model, point-source split-step propagation."""

from .path import PathModel, SamplingReport, Scenario, check_sampling, solve_path
from .propagate import Turbulence, point_source, split_step, split_step_torch
from .screens import ScreenGrid, psd_mvk, screens, structure_function_theory

__all__ = ["PathModel", "SamplingReport", "Scenario", "check_sampling", "solve_path", "Turbulence", "point_source",
           "split_step", "split_step_torch", "ScreenGrid", "psd_mvk", "screens", "structure_function_theory"]
