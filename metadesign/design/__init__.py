"""Stage 2: Eq. 1 supercell phase design and the birefringent discretizer."""

from .discretize import AtomTable, Metric, NearestAtom, brute_force_nearest, optimal_offsets, select_atoms
from .phase import (
    LensChannel,
    SupercellSpec,
    cell_coordinates,
    channel_of_cell,
    design_phase_rows,
    lens_phase,
    paper_channels,
    wrap,
)

__all__ = [
    "AtomTable", "Metric", "NearestAtom", "brute_force_nearest", "optimal_offsets", "select_atoms",
    "LensChannel", "SupercellSpec", "cell_coordinates", "channel_of_cell", "design_phase_rows", "lens_phase",
    "paper_channels", "wrap",
]
