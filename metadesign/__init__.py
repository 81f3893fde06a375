"""metadesign: birefringent metasurfaces for single-shot phase-diversity wavefront sensing.

Stages, one subpackage each, in pipeline order; a stage imports only what lies below it:

* ``optics``: angular spectrum, matrix Fourier transform, Zernike polynomials (shared by the stages);
* ``library`` (1): RCWA unit cells and supercells, the unit-cell library;
* ``design`` (2): Eq. 1 supercell lenses, birefringent binning, nearest-atom discretizer;
* ``layouts`` (3): OASIS/GDS layout, read-back, KLayout cross-check, design rules;
* ``sensing`` (4): the as-fabricated forward model, the typed ``Device``, the torch twin, cameras;
* ``turbulence`` (5): screens, path model, split step, validation, one beacon sample to the sensor;
* ``reconstruction`` (6): datasets, the U-Net, training, evaluation, baselines, estimators, capture import;
* ``studies``: what combines stages (demo, pipeline, compare, tolerance, transfer, Table S2, LPA check).

The shared edges (``conventions``, ``config``, ``validation``, ``io``, ``parallel``, ...) sit below them
all.  Physics kernels are pure functions on arrays in SI units; I/O, CLI and plotting sit at the edges.
See the README's "Conventions" section.
"""

__version__ = "0.1.0"
