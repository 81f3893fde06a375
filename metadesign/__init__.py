"""metadesign: birefringent metasurfaces for single-shot phase-diversity wavefront sensing.

Stages (one subpackage each): ``library`` (RCWA unit cells), ...
Physics kernels are pure functions on arrays in SI units; I/O, CLI and
plotting sit at the edges.  See the README's "Conventions" section.
"""

__version__ = "0.1.0"
