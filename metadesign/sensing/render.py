"""Stage-4 public API: the 8-PSF tensor of a layout for an input field, the
PSF product file, the full-resolution check and the fab study.  The CLI, the
demo and the dataset generator all call these (one code path)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..io import atomic_path, atomic_write_text, json_array, read_product, write_npz
from ..library.locate import file_sha256
from ..validation import ValidationError, check_finite_array
from .detector import Detector
from .device import Device
from .forward import CoarsePupil, full_resolution_frames
from .model import AsFabricated, SensingRecipe, channel_metrics
from .plot import plot_fab_study
from .sensor import NoiseSpec, quadrant_slices
from .transmission import Perturbation, pillar_transmission

__all__ = ["PSFResult", "FabCases", "render_psf", "save_psf", "load_psf", "PSF_FORMAT", "full_resolution_check",
           "fab_study", "FAB_STUDY_COLUMNS", "check_field"]

PSF_FORMAT = "metadesign.psf/1"


@dataclass
class PSFResult:
    frames: np.ndarray  # (2, H, W) float32: power per pixel for unit incident intensity (noisy if noise given)
    tensor: np.ndarray  # (8, S, S) float32: x-pol QI..QIV, y-pol QI..QIV
    pupil: CoarsePupil
    perturbation: Perturbation
    noise: NoiseSpec | None


def check_field(field: np.ndarray, pupil: CoarsePupil, what: str = "input field") -> np.ndarray:
    """A complex field on the coarse pupil grid: shape and finiteness checked."""
    shape = pupil.G.shape[-2:]
    field = np.asarray(field)
    if field.shape != shape:
        raise ValidationError(f"{what}: expected shape {shape} (the coarse pupil grid), got {field.shape}")
    return check_finite_array(what, field).astype(np.complex64)


def render_psf(fab: AsFabricated, sensing: SensingRecipe, field: np.ndarray | None = None,
               pert: Perturbation = Perturbation(), pupil: CoarsePupil | None = None,
               noise: NoiseSpec | None = None, progress=None) -> PSFResult:
    """The as-fabricated sensor frames and 8-PSF tensor of ``fab`` for the incident ``field`` on the coarse
    pupil grid (None: a flat unit plane wave).  ``pupil`` reuses a coarse pupil built for the same
    perturbation and distance (the costly part; build it once per device).  ``noise``: the detector's, after
    rendering (seeded by ``noise.seed``)."""
    if pupil is None:
        pupil = fab.pupil(sensing.sensor.distance, sensing.pupil_grid, pert, progress)
    e_in = None if field is None else check_field(field, pupil)
    shot = Device(pupil, sensing.sensor).render(e_in, Detector(noise) if noise is not None else None)
    return PSFResult(shot.frames, shot.psfs, pupil, pert, noise)


def save_psf(path: str | Path, res: PSFResult, fab: AsFabricated, sensing: SensingRecipe,
             extra: dict | None = None) -> Path:
    """Write the PSF product (``.npz``: ``frames``, ``tensor`` and a JSON ``meta`` with format tag,
    provenance, the channel table and the conventions)."""
    prov = fab.layout.provenance
    meta = {
        "format": PSF_FORMAT, "version": __version__,
        "layout": {"file": str(fab.path) if fab.path else None,
                   "sha256": file_sha256(fab.path) if fab.path else None, "design": prov.get("design")},
        "library_sha256": fab.lib.identity,
        "sensor": sensing.sensor.to_dict(), "pupil_grid": sensing.pupil_grid,
        "pupil": {"block_cells": res.pupil.block, "n": int(res.pupil.G.shape[-1]),
                  "clamped_pillars": res.pupil.n_clamped, "coupling": fab.coupling_name,
                  **({"coupling_model_sha256": fab.coupling_card["weights_sha256"]} if fab.coupling_card else {})},
        "perturbation": res.perturbation.to_dict(),
        "noise": res.noise.to_dict() if res.noise is not None and res.noise.active else None,
        "channels": prov.get("channels") or [
            {"pol": "xy"[p], "k": k, "focal_length_m": c.focal_length, "offset_x_m": c.offset_x,
             "offset_y_m": c.offset_y} for p in range(2) for k, c in enumerate(fab.channels[p], 1)],
        "clear_aperture": fab.aperture, "aperture_m": fab.n_cells * fab.period,
        "conventions": {"frames": "(pol, row, col), pol 0 = x, rows along +y; power per pixel for unit "
                                  "incident intensity",
                        "tensor": "8 x S x S: x-pol QI..QIV, y-pol QI..QIV (QI..QIV = channels k = 1..4 in "
                                  "reading order); area-weighted resampling (power conserved)"},
    } | (extra or {})
    write_npz(path, {"frames": res.frames, "tensor": res.tensor, "meta": json_array(meta)})
    return Path(path)


def load_psf(path: str | Path) -> tuple[dict, dict]:
    """(arrays, meta) of a PSF product; one-line errors on foreign or broken files."""
    z, meta = read_product(path, "PSF product", ("frames", "tensor"), PSF_FORMAT)
    return z, meta


def full_resolution_check(fab: AsFabricated, sensing: SensingRecipe, frames: np.ndarray, window: int,
                          pert: Perturbation = Perturbation(), progress=None) -> dict:
    """Every pillar, no block averaging, on the central ``window x window`` pixels of each quadrant:
    the fast path's relative L2 error per channel (flat incident wavefront)."""
    sensor = sensing.sensor
    rng = np.random.default_rng(pert.seed)

    def rows(r0, r1):
        t, c = pillar_transmission(fab.layout.index_map, fab.layout.atom_widths_nm, fab.lib, pert,
                                   slice(r0, r1), rng, fab.fab_lib, fab.coupling)
        mask = fab.aperture_mask_rows(r0, r1)
        if mask is not None:
            t[~mask] = 0
        return t, c

    full, _ = full_resolution_frames(rows, fab.n_cells, fab.period, fab.wavelength, sensor, fab.tn_scale,
                                     window=window, progress=progress)
    errs = []
    for p in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sensor, k)
            m = full[p][r, c] > 0
            errs.append(float(np.linalg.norm(full[p][r, c][m] - frames[p][r, c][m]) / np.linalg.norm(full[p][r, c][m])))
    return {"window_px": window, "rel_l2_per_channel": errs}


FAB_STUDY_COLUMNS = ["bias_nm", "jitter_nm", "corner_nm", "height_nm", "sidewall_deg", "seed", "pol", "k", "quadrant", "design_focal_length_mm",
                     "focusing_efficiency", "strehl", "focal_shift_mm", "centroid_shift_x_um", "centroid_shift_y_um",
                     "crosstalk", "clamped_pillars"]


@dataclass(frozen=True)
class FabCases:
    """The cases of a fab study: every combination of width ``bias_nm``, ``jitter_nm``, ``corner_nm``, etch
    depth change ``height_nm`` and ``sidewall_deg``, each drawn with ``seeds`` jitter seeds from ``seed``, with
    optional across-wafer gradients of height and sidewall."""

    bias_nm: tuple = (0.0,)
    jitter_nm: tuple = (0.0,)
    corner_nm: tuple = (0.0,)
    height_nm: tuple = (0.0,)
    sidewall_deg: tuple = (90.0,)
    seeds: int = 1
    seed: int = 0
    height_gradient_nm: float = 0.0
    sidewall_gradient_deg: float = 0.0

    def __iter__(self):
        """``(bias, jitter, corner, height, sidewall, seed index)`` of each case, in the study's order."""
        return iter(itertools.product(self.bias_nm, self.jitter_nm, self.corner_nm, self.height_nm,
                                      self.sidewall_deg, range(self.seeds)))

    def __len__(self) -> int:
        return (len(self.bias_nm) * len(self.jitter_nm) * len(self.corner_nm) * len(self.height_nm)
                * len(self.sidewall_deg) * self.seeds)


def fab_study(fab: AsFabricated, sensing: SensingRecipe, cases: FabCases, progress=None) -> list[dict]:
    """Per case (bias x jitter x corner x etch depth x sidewall x seed, :class:`FabCases`) and channel:
    focusing efficiency, Strehl, focal shift, centroid shift, crosstalk (see
    :func:`~metadesign.sensing.model.channel_metrics`).  Height and sidewall cases (with the optional
    across-wafer gradients) need ``fab.fab_lib`` or a library with fab axes."""
    fc, seeds, seed = cases, cases.seeds, cases.seed
    cases = list(fc)
    rows = []
    for i, (b, j, c, h, a, s) in enumerate(cases):
        pert = Perturbation.from_nm(b, b, j, c, seed + s, h, a, fc.height_gradient_nm, fc.sidewall_gradient_deg)
        cp = fab.pupil(sensing.sensor.distance, sensing.pupil_grid, pert)
        label = f"bias {b:+g} jit {j:g} cr {c:g}" + (f" h {h:+g} sw {a:g}" if (h or a != 90) else "")
        for r in channel_metrics(cp, sensing.sensor, fab):
            rows.append({"case": i // seeds, "label": label, "bias_nm": b, "jitter_nm": j, "corner_nm": c,
                         "height_nm": h, "sidewall_deg": a, "coupling": fab.coupling_name,
                         "seed": seed + s, "clamped_pillars": cp.n_clamped, **r,
                         "centroid_shift_x_um": r["centroid_shift_um"][0],
                         "centroid_shift_y_um": r["centroid_shift_um"][1]})
        if progress:
            progress(i + 1, len(cases))
    return rows


def write_fab_study(rows: list[dict], out: Path) -> list[Path]:
    """CSV, JSON and the figure of a fab study in folder ``out``."""
    import csv
    import json

    out.mkdir(exist_ok=True)
    fmt = {"design_focal_length_mm": ".4f", "focusing_efficiency": ".6f", "strehl": ".5f", "focal_shift_mm": ".5f",
           "centroid_shift_x_um": ".4f", "centroid_shift_y_um": ".4f", "crosstalk": ".5f"}
    with atomic_path(out / "fab-study.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(FAB_STUDY_COLUMNS)
            for r in rows:
                w.writerow([format(r[c], fmt.get(c, "")) for c in FAB_STUDY_COLUMNS])
    fig = plot_fab_study(rows, out / "fab-study.png")
    atomic_write_text(out / "fab-study.json", json.dumps(rows, indent=1, default=float))
    return [out / "fab-study.csv", out / "fab-study.json", Path(fig)]
