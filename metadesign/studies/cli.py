"""The commands of the studies that combine stages, one CLI module per area:

* :mod:`.cli_main`: ``demo`` and ``run`` (a pipeline recipe through every stage);
* :mod:`.cli_compare`: ``compare`` and ``retrieve``;
* :mod:`.cli_stage6`: ``transfer``, ``tolerance``, ``table-s2``, ``codesign`` and ``dataset synth-captures``;
* :mod:`.cli_lpa`: ``library lpa-check``;
* :mod:`.cli_supercells`: ``library supercells|coupling|peds|ladder|patches|active``;
* :mod:`.cli_coupling_check`: ``library coupling-check|coupling-sweep``;
* :mod:`.cli_loop`: ``loop`` (the closed loop in time);
* :mod:`.cli_loop_map`: ``loop-map`` (the loop over rate or latency x f_G x Rytov);
* :mod:`.cli_polcam`: ``polcam`` (which polarisation camera to buy).

:mod:`metadesign.cli` assembles them (:data:`STUDY_MODULES`, in the order of the help)."""

from __future__ import annotations

from . import (cli_compare, cli_coupling_check, cli_loop, cli_loop_map, cli_lpa, cli_main, cli_polcam, cli_stage6,
               cli_supercells)
from .cli_compare import BUILTIN_ESTIMATORS

__all__ = ["register", "register_main", "STUDY_MODULES", "BUILTIN_ESTIMATORS"]

#: the study CLIs after the stage CLIs, in the order of the help (each adds its commands: top-level ones, and
#: actions to the stage groups it is given)
STUDY_MODULES = (cli_compare, cli_stage6, cli_lpa, cli_supercells, cli_coupling_check, cli_loop, cli_loop_map,
                 cli_polcam)


def register_main(sub) -> None:
    """``demo`` and ``run``: the commands a new user starts with."""
    cli_main.register(sub)


def register(sub, groups: dict) -> None:
    """Add the study commands: top-level ones to ``sub``, the stage groups' actions to ``groups``."""
    for mod in STUDY_MODULES:
        mod.register(sub, groups)
