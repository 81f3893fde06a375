"""The design rules, named once: every check (``layout verify``, the tiled verification, the demo, the
pipeline's report) and every label reads them from here."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["DesignRules", "DESIGN_RULES"]


@dataclass(frozen=True)
class DesignRules:
    """Minimum pillar width (``min_feature_nm``) and minimum gap between neighbouring pillars
    (``min_gap_nm``), in nm on the mask."""

    min_feature_nm: int = 100
    min_gap_nm: int = 150

    def label(self) -> str:
        return f"min feature {self.min_feature_nm} nm, min gap {self.min_gap_nm} nm"


#: the rules of the paper's a-Si process (pillar widths >= 100 nm, gaps >= 150 nm)
DESIGN_RULES = DesignRules()
