"""The coupling check of a design as one study (``metadesign library coupling-check``): its inputs checked
together (:class:`CouplingCheckRequest`), then the devices made from them, checked, measured
(:func:`~metadesign.studies.coupling_check.coupling_check`) and written (:func:`run_coupling_check`)."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..design.store import design_file, load_design
from ..execution import SERIAL, Execution, scratch_path
from ..io import atomic_write_text
from ..library.locate import file_sha256
from ..library.store import load_library
from ..library.peds import PedsModel, find_peds, load_peds
from ..library.supercells import remove_partial
from ..paths import product as packaged
from ..reconstruction.dataset import load_device
from ..sensing.model import AsFabricated, load_sensing_recipe
from ..sensing.transmission import Perturbation
from ..validation import ValidationError
from .certified import CertifiedSettings
from .coupling_check import (
    CASES,
    CertifiedCheck,
    coupling_check,
    plot_case_metrics,
    plot_coupling_frames,
)
from .lpa import Downstream

__all__ = ["CouplingCheckRequest", "run_coupling_check"]


@dataclass(frozen=True)
class CouplingCheckRequest:
    """What a coupling check measures: ``design`` (a design folder) and optionally its ``compensated``
    design, under the LPA and the supercell ``coupling_model`` (None: the one fitted against the library),
    made with ``pert`` (its unit cells from ``fab_library`` when given: the height and wall axes), on the
    sensor of ``sensor`` (a sensing recipe; None: the paper's) or of ``downstream.dataset``; ``certified``:
    the certified cases' settings (``supercells`` 0: none).  The options' rules are checked on construction
    (ValidationError, one line)."""

    design: Path
    compensated: Path | None = None
    coupling_model: str | None = None
    sensor: str | None = None
    fab_library: str | None = None
    pert: Perturbation = Perturbation()
    downstream: Downstream | None = None
    certified: CertifiedSettings = CertifiedSettings(supercells=0)

    def __post_init__(self) -> None:
        c, p = self.certified, self.pert
        if c.ring_supercells and not c.supercells:
            raise ValidationError("--ring: the neighbour ring adds to the certified model; give --certified N")
        if c.ring_supercells > c.supercells:
            raise ValidationError(f"--ring {c.ring_supercells}: the ring is solved on some of the certified sample's "
                                  f"supercells, so at most --certified {c.supercells}")
        if c.ring_supercells and c.ring_supercells < c.replicates:
            raise ValidationError(f"--ring {c.ring_supercells}: at least one supercell per replicate (--replicates "
                                  f"{c.replicates})")
        if c.reoptimise and not c.supercells:
            raise ValidationError("--reoptimise: re-chooses the sampled supercells' atoms; give --certified N")
        if c.reoptimise == 1:
            raise ValidationError("--reoptimise 1: K counts the atom itself, so at least 2 (0: none)")
        if c.reoptimise and (p.bias_x or p.bias_y or p.jitter or p.height or p.sidewall_deg != 90):
            raise ValidationError("--reoptimise: the atoms are re-chosen for the nominal device (no --bias-nm, "
                                  "--jitter-nm, --height-nm or --sidewall-deg)")
        if c.supercells and c.supercells < 2 * c.replicates:
            raise ValidationError(f"--certified {c.supercells}: at least two supercells per replicate "
                                  f"(--replicates {c.replicates}), so >= {2 * c.replicates}")


def _check_fab_axes(fab, pert: Perturbation) -> None:
    """An etch-depth error or a sloped wall needs a fab library that spans it (ValidationError)."""
    if not (pert.height or pert.sidewall_deg != 90):
        return
    F = fab.fab_lib if fab.fab_lib is not None else fab.lib
    if F.fab is None:
        raise ValidationError("--height-nm / --sidewall-deg need a library with fab axes: pass --fab-library "
                              "(e.g. library/paper-fab.npz)")
    height_nm = pert.height * 1e9
    hs = (np.asarray(F.fab["heights"]) - fab.lib.stack.height) * 1e9
    if not hs.min() - 1e-6 <= height_nm <= hs.max() + 1e-6:
        raise ValidationError(f"--height-nm {height_nm:g}: the fab library spans {hs.min():+.0f} to "
                              f"{hs.max():+.0f} nm")
    ws = np.asarray(F.fab["sidewalls"], float)
    if not ws.min() - 1e-9 <= pert.sidewall_deg <= ws.max() + 1e-9:
        raise ValidationError(f"--sidewall-deg {pert.sidewall_deg:g}: the fab library spans {ws.min():g} to "
                              f"{ws.max():g} deg")


def _devices(req: CouplingCheckRequest) -> tuple[dict, dict]:
    """``(designs, fabs)``: the design (and the compensated one) and each case's device."""
    designs = {"coupled": load_design(req.design)}
    fab = AsFabricated.from_design(designs["coupled"])
    if req.fab_library:
        fab.fab_lib = load_library(req.fab_library)
    _check_fab_axes(fab, req.pert)
    fabs = {"lpa": fab, "coupled": fab.with_coupling("supercell", req.coupling_model)}
    if req.compensated:
        designs["compensated"] = load_design(req.compensated)
        fc = AsFabricated.from_design(designs["compensated"])
        fc.fab_lib = fab.fab_lib
        fabs["compensated"] = fc.with_coupling("supercell", req.coupling_model)
        fabs["compensated_lpa"] = fc
    return designs, fabs


def _sensor(req: CouplingCheckRequest, fab):
    """``(sensor, pupil grid)``: the dataset's device's (its pupil made with this design), else the recipe's."""
    if req.downstream is not None:
        dev = load_device(req.downstream.dataset)
        if dev.pupil.block != fab.pupil_block(dev.pupil.G.shape[-1]):
            raise ValidationError(f"{req.downstream.dataset}: its device's pupil ({dev.pupil.block}-cell blocks) is "
                                  "not this design's on that grid: use the dataset made with this design")
        return dev.sensor, dev.pupil.G.shape[-1]
    sr = load_sensing_recipe(req.sensor or packaged("sensing", "paper.toml"))
    return sr.sensor, sr.pupil_grid


#: core-seconds of one supercell's certified (PEDS) solves, all levels (measured: 0.09-0.12 on the paper design)
PEDS_CORE_S = 0.12


def _certified_plan(req: CouplingCheckRequest, fab, run: Execution) -> CertifiedSettings:
    """The certified settings with their PEDS model loaded (a file of another kind refused now, not after the
    solves), a sample no larger than the device's supercells, and the cost said before the work."""
    c = req.certified
    peds = c.peds if isinstance(c.peds, PedsModel) else load_peds(c.peds if c.peds is not None else find_peds(fab.lib),
                                                                  fab.lib)
    n_super = (fab.n_cells // 2) ** 2
    total = c.supercells + c.ring_supercells * 3 + c.supercells * max(0, c.reoptimise - 1) * 4 * c.reoptimise_sweeps
    if c.supercells > n_super:
        raise ValidationError(f"--certified {c.supercells}: more than the device's {n_super:,} supercells (a sample "
                              "that large costs more than solving every supercell once)")
    hours = total * PEDS_CORE_S / 3600
    run.log(f"certified: about {total:,} supercell solves at {len(peds.harmonics)} levels, ~{hours:.2g} core-hours "
            f"(~{hours / max(1, run.workers):.2g} h on {max(1, run.workers)} workers)")
    return replace(c, peds=peds)


def run_coupling_check(req: CouplingCheckRequest, out: Path, run: Execution = SERIAL) -> dict:
    """The coupling check of ``req`` into the folder ``out``: ``coupling-check.json``, ``coupling-frames.png``
    and (with certified cases) ``coupling-metrics.png``; the certified solves resumable in ``OUT.partial/``
    (removed at the end)."""
    partial = scratch_path(out)
    designs, fabs = _devices(req)
    if req.certified.supercells:
        req = replace(req, certified=_certified_plan(req, fabs["lpa"], run))
    sensor, grid = _sensor(req, fabs["lpa"])
    run.log(f"coupling-check: {req.design} ({', '.join(CASES[k] for k in fabs)}) ...")
    cert = CertifiedCheck(req.certified, partial, designs) if req.certified.supercells else None
    rep, frames = coupling_check(fabs, sensor, grid, req.pert, req.downstream, cert, run)
    rep["figure"] = str(plot_coupling_frames(frames, sensor, out / "coupling-frames.png"))
    if cert:
        rep["metrics_figure"] = str(plot_case_metrics(rep, out / "coupling-metrics.png"))
    rep["coupling_model_sha256"] = fabs["coupled"].coupling_card["weights_sha256"]
    rep["design"] = {"path": str(req.design), "sha256": file_sha256(design_file(req.design))}  # sweeps match it
    atomic_write_text(out / "coupling-check.json", json.dumps(rep, indent=1))
    remove_partial(partial)
    return rep
