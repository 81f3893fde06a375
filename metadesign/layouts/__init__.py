"""Stage 3: OASIS/GDS layout writer (gdstk), read-back, KLayout cross-check, design rules, previews."""

from .reader import LayoutContents, check_file, drc_check, read_layout, read_layout_klayout, verify_against_design
from .writer import LayoutOptions, layout_geometry, layout_library, snap_widths, write_layout

__all__ = ["LayoutContents", "check_file", "drc_check", "read_layout", "read_layout_klayout", "verify_against_design",
           "LayoutOptions", "layout_geometry", "layout_library", "snap_widths", "write_layout"]
