"""The design rules, named once: every check (``layout verify``, the tiled verification, the demo, the
pipeline's report) and every label reads them from here."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["DesignRules", "DESIGN_RULES"]


@dataclass(frozen=True)
class DesignRules:
    """Minimum pillar width (``min_feature_nm``) and minimum gap between neighbouring pillars
    (``min_gap_nm``), in nm on the mask; ``window_cells``: the side, in cells, of the window the geometric
    (KLayout) checks run on where they cannot run on every pillar (``layout verify --drc-window-cells``)."""

    min_feature_nm: int = 100
    min_gap_nm: int = 150
    window_cells: int = 64

    def limits(self) -> dict:
        """The two rules as a report records them."""
        return {"min_feature_nm": self.min_feature_nm, "min_gap_nm": self.min_gap_nm}

    def label(self) -> str:
        return f"min feature {self.min_feature_nm} nm, min gap {self.min_gap_nm} nm"


#: the rules of the paper's a-Si process (pillar widths >= 100 nm, gaps >= 150 nm)
DESIGN_RULES = DesignRules()
