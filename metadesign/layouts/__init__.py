"""Stage 3: OASIS/GDS layout writer (gdstk), read-back, KLayout cross-check, design rules, previews;
:func:`verify` checks a written layout against its design by whichever method fits (one report type)."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562)
_EXPORTS = {
    "LayoutContents": "reader", "check_file": "reader", "drc_check": "reader", "read_layout": "reader",
    "read_layout_klayout": "reader", "verify_against_design": "reader", "LayoutOptions": "writer",
    "layout_geometry": "writer", "layout_library": "writer", "snap_widths": "writer", "write_layout": "writer",
    "open_layout": "reader", "metasurface_component": "component", "MadeLayout": "make", "make_layout": "make", "DESIGN_RULES": "rules", "DesignRules": "rules",
    "verify": "verification", "VerifyReport": "verification", "VerifyOptions": "verification",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
