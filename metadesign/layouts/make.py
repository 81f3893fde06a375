"""Design -> layout -> read-back -> design rules: the one sequence every caller runs (the demo, the pipeline,
a dataset whose layout is missing, ``layout write`` + ``layout verify``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .reader import LayoutContents, drc_check, read_layout, read_layout_klayout, verify_against_design
from .writer import LayoutOptions, write_layout

__all__ = ["MadeLayout", "make_layout"]


@dataclass
class MadeLayout:
    """A written layout and its checks: ``write`` (the writer's report), ``verify`` (gdstk read-back against
    the design), ``verify_klayout`` (the independent reader's, when asked), ``drc`` (design rules, when
    asked) and the read-back ``contents``."""

    path: Path
    write: dict
    verify: dict
    contents: LayoutContents
    verify_klayout: dict | None = None
    drc: dict | None = None

    @property
    def exact(self) -> bool:
        return bool(self.verify["exact"] and (self.verify_klayout is None or self.verify_klayout["exact"]))

    @property
    def passed(self) -> bool:
        return self.exact and (self.drc is None or bool(self.drc["passed"]))


def make_layout(design, target: str | Path, *, klayout: bool = False, drc: bool = True,
                opts: LayoutOptions = LayoutOptions()) -> MadeLayout:
    """Write ``design`` as the OASIS file ``target`` (+ side-car), read it back exactly (gdstk; and KLayout
    with ``klayout``) and check the design rules (:data:`~.rules.DESIGN_RULES`, with ``drc``)."""
    target = Path(target)
    rep = write_layout(design, target, "oas", opts)
    lc = read_layout(target)
    v = verify_against_design(lc, design, opts.grid_nm)
    k = verify_against_design(read_layout_klayout(target), design, opts.grid_nm) if klayout else None
    return MadeLayout(target, rep, v, lc, k, drc_check(lc) if drc else None)
