"""Synthetic camera captures of a dataset's received phases shown on an SLM (``metadesign dataset
synth-captures``): the study that feeds :mod:`metadesign.reconstruction.captures` (import) in tests and in
the fab-to-lab transfer demo.  The camera, relay and exposure models are :mod:`metadesign.sensing.camera`."""

from __future__ import annotations

import csv
import io
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..execution import fresh_scratch, publish_scratch, remove_scratch, scratch_path
from ..io import atomic_path, atomic_write_text
from ..outputs import product, write_marker, zarr_input
from ..reconstruction.data import PSFDataset
from ..reconstruction.dataset import load_device
from ..sensing.device import Device
from ..sensing.camera import Alignment, CameraSpec, expose, misaligned_frames, slm_pupil_field, write_frame
from ..validation import ValidationError

__all__ = ["synth_captures", "CaptureSession"]


@dataclass(frozen=True)
class CaptureSession:
    """What a synthetic capture session records: the first ``samples`` of the phases' ``split`` (None: all),
    in file format ``fmt``, with ``flats`` flat-wavefront and ``darks`` dark captures, the last ``saturate``
    samples over-exposed, the noise drawn from ``seed``."""

    samples: int | None = None
    split: str = "all"
    fmt: str = "png"
    flats: int = 4
    darks: int = 4
    saturate: int = 0
    seed: int = 0

    def __post_init__(self):
        if self.fmt not in _EXTENSIONS:
            raise ValidationError(f"format: expected one of {', '.join(_EXTENSIONS)}, got {self.fmt!r}")

    @property
    def ext(self) -> str:
        return _EXTENSIONS[self.fmt]


_EXTENSIONS = {"png": ".png", "tiff": ".tif", "npy": ".npy", "fits": ".fits"}


@dataclass(frozen=True)
class _Job:
    """One synthesis: the phases' dataset and the device's, the session, the camera and its alignment."""

    phases: Path
    device: Path
    session: CaptureSession
    camera: CameraSpec
    alignment: Alignment
    progress: object = None


def synth_captures(phases: str | Path, device: str | Path, out: str | Path, alignment: Alignment = Alignment(),
                   camera: CameraSpec = CameraSpec(), session: CaptureSession = CaptureSession(),
                   progress=None) -> dict:
    """Write synthetic captures into ``out``: ``frames/NNNNNN-{x,y}.EXT``, ``slm/NNNNNN.npy`` (phase, rad),
    ``manifest.csv`` (sample, frame_x, frame_y, slm_phase, rytov, split), ``flat/``+``flat.csv`` (flat-
    wavefront captures), ``dark/`` (dark frames), ``truth.json`` (alignment, camera, device; for tests).

    ``phases``: the dataset whose received phases the SLM shows (``split`` of it, first ``samples``);
    ``device``: the dataset (older datasets: or their ``device-pupil.npz``) whose device renders the frames; the sensor
    and geometry come from ``phases``.  The last ``saturate`` samples are over-exposed 2x (clipped)."""
    final = Path(out)
    if final.exists() and (not final.is_dir() or any(final.iterdir())):
        raise ValidationError(f"-o/--output {final}: exists and is not empty (captures are written into a new folder)")
    with product(final, "captures", {"PHASES": zarr_input(phases), "--device": device},
                 scratch=(scratch_path(final),)):
        return _synth_captures(_Job(Path(phases), Path(device), session, camera, alignment, progress), final)


def _synth_captures(job: _Job, final: Path) -> dict:
    dev = load_device(job.device.parent if job.device.suffix == ".npz" else job.device)
    geo_src = load_device(job.phases)
    ds = PSFDataset(job.phases, job.session.split, limit=job.session.samples)
    if len(ds) == 0:
        raise ValidationError(f"{job.phases}: the {job.session.split} split is empty (no samples to capture)")
    out = fresh_scratch(final)  # OUT.partial, renamed when complete: a failure leaves no capture folder
    try:
        rep = _synth(job, ds, Device(dev.pupil, geo_src.sensor, geo_src.crop), out)
        write_marker(out, "captures")
        if final.exists():  # empty but for the marker (refused otherwise, above)
            shutil.rmtree(final)
        publish_scratch(out, final)
    except BaseException:
        remove_scratch(out)
        raise
    return {**rep, "output": str(final)}


def _synth(job: _Job, ds, dev: Device, out: Path) -> dict:
    """The captures of ``ds``'s samples by the device ``dev`` (its pupil, the phases' sensor and crop) into
    ``out``."""
    cp, sensor, geom = dev.pupil, dev.sensor, dev.geometry
    se, camera, alignment, progress = job.session, job.camera, job.alignment, job.progress
    n, ext, flats, darks, saturate, seed = len(ds), se.ext, se.flats, se.darks, se.saturate, se.seed
    for sub in ("frames", "slm", "flat", "dark"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    shape = (sensor.height_px, sensor.width_px)
    hot = camera.hot_map(shape)
    root = np.random.SeedSequence(seed)
    rows = []
    labels = {0: "train", 1: "val", 2: "test"}
    split_of = ds.info.split
    for j in range(n):
        s = ds.get(j)
        i = s["index"]
        ap = np.abs(s["received"]) > 0
        phi = np.where(ap, np.angle(s["received"]), 0.0).astype(np.float32)
        e_in = slm_pupil_field(phi, geom, cp.G.shape[-1])
        fr = misaligned_frames(cp, sensor, e_in, alignment)
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1, j)))
        counts = expose(fr, camera, rng, hot, overexpose=2.0 if j >= n - saturate else 1.0)
        name = f"{j:06d}"
        write_frame(out / "frames" / f"{name}-x{ext}", counts[0])
        write_frame(out / "frames" / f"{name}-y{ext}", counts[1])
        with atomic_path(out / "slm" / f"{name}.npy") as tmp, open(tmp, "wb") as fh:
            np.save(fh, phi, allow_pickle=False)
        rows.append({"sample": name, "frame_x": f"frames/{name}-x{ext}", "frame_y": f"frames/{name}-y{ext}",
                     "slm_phase": f"slm/{name}.npy", "rytov": f"{s['rytov']:.6g}",
                     "split": labels[int(split_of[i])]})
        if progress:
            progress(j + 1, n + flats + darks)
    flat_rows = []
    fr0 = misaligned_frames(cp, sensor, None, alignment)
    for j in range(flats):
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2, j)))
        counts = expose(fr0, camera, rng, hot)
        for p, pol in enumerate("xy"):
            write_frame(out / "flat" / f"flat{j:02d}-{pol}{ext}", counts[p])
        flat_rows.append({"frame_x": f"flat/flat{j:02d}-x{ext}", "frame_y": f"flat/flat{j:02d}-y{ext}"})
        if progress:
            progress(n + j + 1, n + flats + darks)
    for j in range(darks):
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(3, j)))
        write_frame(out / "dark" / f"dark{j:02d}{ext}", expose(np.zeros(shape), camera, rng, hot))
        if progress:
            progress(n + flats + j + 1, n + flats + darks)
    _write_csv(out / "manifest.csv", rows)
    _write_csv(out / "flat.csv", flat_rows)
    truth = {"alignment": alignment.to_dict(), "camera": camera.to_dict(), "phases": str(job.phases),
             "device": str(job.device), "samples": n,
             "saturated": [r["sample"] for r in rows[n - saturate:]] if saturate else [],
             "hot_pixels": int(hot.sum()), "format": se.fmt, "seed": int(root.entropy)}
    atomic_write_text(out / "truth.json", json.dumps(truth, indent=1))
    return {"samples": n, "flats": flats, "darks": darks, "format": se.fmt,
            "alignment": alignment.to_dict(), "saturated": len(truth["saturated"])}


def _write_csv(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["sample"])
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(path, buf.getvalue())
