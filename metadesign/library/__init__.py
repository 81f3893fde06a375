"""Stage 1: the RCWA unit-cell library (rectangular pillars, both polarisations)."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562)
_EXPORTS = {
    "CellResult": "rcwa", "Factorization": "rcwa", "SolverSettings": "rcwa", "Stack": "rcwa", "Truncation": "rcwa",
    "fabry_perot_t": "rcwa", "solve_cell": "rcwa", "UnitCellLibrary": "store", "export_csv": "store",
    "load_library": "store", "save_library": "store",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
