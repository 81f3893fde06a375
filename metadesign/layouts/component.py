"""The metasurface as a gdsfactory ``Component`` (optional: ``pip install 'metadesign[gdsfactory]'``), so a
mask designer places it with the rest of a chip in gdsfactory's own terms.

gdsfactory (9, on KLayout's kfactory) works in micrometres on a 1 nm database unit, the layout's own, so
the written OASIS/GDS is imported as it is: one instance per pillar of the atom cells, nothing
flattened (51 M instances for the paper design are KLayout references, as in the file).  The layout is
read through KLayout (the independent reader that verifies it), the Component named after the layout
file's content so that two metasurfaces in one session never share a cell.
"""

from __future__ import annotations

from pathlib import Path

from ..tasks import file_key
from ..validation import InputError

__all__ = ["metasurface_component"]


def metasurface_component(layout: str | Path, name: str | None = None):
    """The written layout (OASIS or GDS) as a gdsfactory Component: micrometre coordinates centred on the
    aperture, the pillars on layer (1, 0) as the layout has them (``metadesign.layouts.writer``)."""
    try:
        import gdsfactory as gf
    except ModuleNotFoundError:
        raise InputError("metasurface_component needs gdsfactory: pip install 'metadesign[gdsfactory]'") from None
    p = Path(layout)
    if not p.is_file():
        raise InputError(f"{layout}: no such layout file")
    c = gf.import_gds(p)
    if c.kcl.dbu != 0.001:
        raise InputError(f"{layout}: database unit {c.kcl.dbu} um; the metasurface's layouts use 1 nm (0.001 um)")
    c.name = name or f"METASURFACE_{file_key(p)[:12]}"
    return c
