"""Stage 1: the RCWA unit-cell library (rectangular pillars, both polarisations)."""

from .rcwa import CellResult, Factorization, SolverSettings, Stack, Truncation, fabry_perot_t, solve_cell
from .store import UnitCellLibrary, export_csv, load_library, save_library

__all__ = [
    "CellResult", "Factorization", "SolverSettings", "Stack", "Truncation", "fabry_perot_t", "solve_cell",
    "UnitCellLibrary", "export_csv", "load_library", "save_library",
]
