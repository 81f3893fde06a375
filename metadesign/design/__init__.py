"""Stage 2: Eq. 1 supercell phase design and the birefringent discretizer."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562)
_EXPORTS = {
    "AtomTable": "discretize", "Metric": "discretize", "NearestAtom": "discretize",
    "brute_force_nearest": "discretize", "optimal_offsets": "discretize", "select_atoms": "discretize",
    "LensChannel": "phase", "SupercellSpec": "phase", "cell_coordinates": "phase", "channel_of_cell": "phase",
    "design_phase_rows": "phase", "lens_phase": "phase", "paper_channels": "phase", "wrap": "phase",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
