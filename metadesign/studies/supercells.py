"""The supercell studies, one module each (this module re-exports their names):

* :mod:`.supercell_table`: the supercell table of a design (its recipe, which rows to solve, the resumable
  build) and the active-learning pool;
* :mod:`.supercell_ladder`: the convergence ladder of a table's labels;
* :mod:`.supercell_patches`: 4 x 4 patches against their four supercells (the neighbour ring);
* :mod:`.coupling_cert`: the coupling model fitted and certified on a table;
* :mod:`.peds_cert`: the PEDS surrogate calibrated and certified on a converged table;
* :mod:`.supercell_errors`: the error statistics they share."""

from __future__ import annotations

from .coupling_cert import (  # noqa: F401
    CouplingFit,
    CouplingInputs,
    certify_coupling,
    check_coupling_inputs,
    coupling_study,
    load_coupling_inputs,
    plot_coupling,
)
from .peds_cert import PedsSettings, _solve_seconds, certify_peds, load_peds_inputs, plot_peds, select_levels  # noqa: F401
from .supercell_errors import _by_source, _error_histogram, _stats  # noqa: F401
from .supercell_ladder import convergence_ladder
from .supercell_patches import (  # noqa: F401
    ALIGNED,
    PATCH_MODELS,
    PatchSettings,
    _patch_task,
    _ring_section,
    _window_section,
    design_patches,
    patch_study,
    plot_patches,
    solve_patches,
)
from .supercell_table import (  # noqa: F401
    POOL_SEED_OFFSET,
    RowDraw,
    SOURCES,
    SUPERCELL_SECTIONS,
    SupercellRecipe,
    _design_widths,
    build_table,
    design_source,
    load_supercell_recipe,
    pool_widths,
    sample_rows,
    supercell_need,
)

__all__ = ["SupercellRecipe", "load_supercell_recipe", "sample_rows", "build_table", "pool_widths", "convergence_ladder",
           "patch_study", "design_source", "SOURCES", "certify_coupling",
           "plot_coupling", "certify_peds", "plot_peds", "select_levels", "design_patches", "solve_patches",
           "plot_patches", "supercell_need", "PedsSettings", "load_peds_inputs",
           "PatchSettings", "RowDraw", "CouplingFit"]
