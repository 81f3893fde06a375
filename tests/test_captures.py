"""Captured frames: synthetic captures through a perturbed device on a misaligned camera (shot and read
noise, dark offset, hot pixels, 16-bit PNG/TIFF) are imported; the calibration recovers the relay
misalignment, the imported tensors match the nominal-geometry renders, the SLM propagation gives the
numpy turbulence stage's NPiB, and bad inputs are one line, exit 2, nothing written."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")

TRUE = dict(shift_x_px=3.4, shift_y_px=-2.2, rotation_deg=0.4, scale=1.008)


def _perturbed_device(base, layout):
    """The same layout as made by a process with +10 / -10 nm width bias (x / y) and 3 nm jitter: a tiny
    dataset whose device pupil the synthetic captures render through (the reference model is nominal)."""
    from conftest import tiny_dataset_recipe

    from metadesign.reconstruction.dataset import build_dataset, load_dataset_recipe

    rec = load_dataset_recipe(tiny_dataset_recipe(base, layout, samples=2, shard=2, extra=(
        "\n[fabrication]\nbias_x_nm = 10\nbias_y_nm = -10\njitter_nm = 3\nseed = 1\n")))
    build_dataset(rec, base / "device")
    return base / "device"


@pytest.fixture(scope="module")
def captures(tmp_path_factory, tiny_dataset, demo_products):
    from metadesign.sensing.camera import Alignment, CameraSpec
    from metadesign.studies.captures import CaptureSession, synth_captures

    base = tmp_path_factory.mktemp("captures")
    dev = _perturbed_device(base, demo_products["layout"])
    cam = CameraSpec(photons_at_peak=1e6, read_noise_e=2.0, hot_pixels=15)
    synth_captures(tiny_dataset, dev, base / "cap", Alignment(**TRUE), cam,
                   CaptureSession(samples=5, saturate=1, fmt="png", seed=2))
    return {"cap": base / "cap", "device": dev, "ref": tiny_dataset, "base": base}


def _render(dev_dataset, phases):
    from metadesign.reconstruction.dataset import load_device, normalise_psf
    from metadesign.sensing.camera import slm_pupil_field
    from metadesign.sensing.forward import sensor_frames
    from metadesign.sensing.sensor import psf_tensor

    dev = load_device(dev_dataset)
    out = []
    for phi in phases:
        e = slm_pupil_field(phi, dev.geometry, dev.pupil_n)
        out.append(normalise_psf(psf_tensor(sensor_frames(dev.pupil, dev.sensor, e), dev.sensor))[0])
    return np.stack(out)


def test_import_recovers_the_misalignment_and_the_tensors(captures, tmp_path):
    from metadesign.reconstruction.captures import import_captures
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.sensing.camera import Alignment

    cap = captures["cap"]
    rep = import_captures(cap, tmp_path / "imp", cap / "flat.csv", captures["ref"], sorted((cap / "dark").glob("*")))
    cal = rep["calibration"]
    fitted = Alignment(**cal["alignment"])
    true = Alignment(**TRUE)
    shape = (512, 640)
    pts = np.array([[0, 0], [639, 0], [0, 511], [639, 511], [160, 128], [480, 384]], float)
    err = np.linalg.norm(fitted.forward(pts, shape) - true.forward(pts, shape), axis=1)
    # within a pixel everywhere on the frame (the bias moves the spots a little: the reference is nominal;
    # through the nominal device itself the fit is exact to 0.1 px, test_synthetic_captures_...)
    assert err.max() < 1.0, (err, cal["alignment"])
    assert cal["hot_pixels"] == 15
    assert rep["saturated"] == 1 and rep["samples"] == 5  # flagged and kept
    ds = PSFDataset(tmp_path / "imp", "all")
    assert ds.info.attrs["propagation"] == "slm"
    phases = [np.load(cap / "slm" / f"{j:06d}.npy") for j in range(4)]
    got = np.stack([ds.get(j)["psf"] for j in range(4)])
    want = _render(captures["device"], phases)
    # compare where the camera saw the light: tensor pixels whose window lies wholly on the frame (the
    # relay shifts ~3 px of each window off the frame; this small device spreads light to the edges)
    from metadesign.reconstruction.captures import aligned_tensor, read_frame
    from metadesign.reconstruction.dataset import load_device, normalise_psf

    sensor = load_device(captures["ref"]).sensor
    ones = np.ones((2, 512, 640))
    seen = aligned_tensor(ones, sensor, fitted, sensor.tensor_size)[0] > 0.999 * aligned_tensor(
        ones, sensor, Alignment(), sensor.tensor_size)[0]
    assert 0.9 < seen.mean() < 1.0

    def rel_err(a, b):
        a, b = a * seen, b * seen
        a = a / a.sum(axis=(-3, -2, -1), keepdims=True)
        b = b / b.sum(axis=(-3, -2, -1), keepdims=True)
        return np.sqrt(((a - b) ** 2).sum(axis=(-3, -2, -1)) / (b**2).sum(axis=(-3, -2, -1)))

    rel = rel_err(got, want)
    assert rel.max() < 0.02, rel
    # the same captures cropped at the nominal windows (no calibration) are measurably worse
    dark = np.mean([read_frame(p)[0] for p in sorted((cap / "dark").glob("*"))], axis=0)
    fr = np.stack([read_frame(cap / "frames" / f"000000-{p}.png")[0] - dark for p in "xy"])
    raw = normalise_psf(aligned_tensor(fr, sensor, Alignment(), sensor.tensor_size)[0])[0]
    assert rel_err(raw, want[0]) > 3 * rel[0]


def test_slm_propagation_matches_the_numpy_turbulence_stage(captures, tmp_path):
    """Through the SLM screen: the torch PiB of flat, half and full phase corrections equals the numpy
    Turbulence.power_in_bucket of the receiver field vacuum x exp(i phi) (the point beacon through vacuum,
    then the SLM); the full correction gives NPiB 1."""
    from metadesign.reconstruction.captures import import_captures
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.losses import PiB
    from metadesign.turbulence.propagate import Turbulence

    cap = captures["cap"]
    import_captures(cap, tmp_path / "imp", cap / "flat.csv", captures["ref"])
    ds = PSFDataset(tmp_path / "imp", "all", screens=True, limit=2)
    c0, a = ds.crop()
    sc = ds.scenario()
    pib = PiB(sc, c0, a, double=True)
    tb = Turbulence(sc, check=False)
    tb.active = np.ones(sc.n_screens, bool)
    for j in range(2):
        s = ds.get(j)
        phi = np.where(np.abs(s["received"]) > 0, np.angle(s["received"]), 0.0)
        full = np.zeros((sc.n_grid, sc.n_grid))
        full[c0:c0 + a, c0:c0 + a] = phi
        field = tb.vacuum * np.exp(1j * full)
        scr = torch.from_numpy(s["screens"].astype(np.float64))[None]
        for frac, mode in ((0.0, "none"), (0.5, "phase"), (1.0, "phase")):
            got = float(pib.npib_phase(torch.from_numpy(frac * phi)[None], scr)[0])
            f = tb.vacuum * np.exp(1j * frac * full) if frac < 1 else field
            want = tb.power_in_bucket(f, mode, s["screens"])
            assert got == pytest.approx(want, rel=1e-4), (j, frac, got, want)
        assert got == pytest.approx(1.0, abs=1e-4)


def _edit_manifest(src, dst, fn):
    shutil.copytree(src, dst)
    with open(dst / "manifest.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    rows = fn(rows)
    with open(dst / "manifest.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return dst


def _run(argv, capsys):
    from conftest import run_main

    return run_main(argv, capsys)


def test_bad_captures_are_one_line_and_write_nothing(captures, tmp_path, capsys):
    cap, ref = captures["cap"], captures["ref"]

    def imp(folder, *extra):
        out = tmp_path / "out"
        rc, _, err = _run(["dataset", "import", folder, "-o", out, "--calibration", cap / "flat.csv",
                           "--reference", ref, *extra], capsys)
        assert rc == 2 and len(err) == 1 and err[0].startswith("metadesign: error:"), (rc, err)
        assert not out.exists() and not list(tmp_path.glob("*.partial")), "files written on exit 2"
        return err[0]

    def drop_frame(rows):
        rows[2]["frame_y"] = "frames/missing.png"
        return rows

    assert "no such file" in imp(_edit_manifest(cap, tmp_path / "a", drop_frame))
    assert "listed twice" in imp(_edit_manifest(cap, tmp_path / "b", lambda r: r + [r[0]]))
    c = _edit_manifest(cap, tmp_path / "c", lambda r: r)
    from PIL import Image

    Image.fromarray(np.zeros((100, 120), np.uint16)).save(c / "frames" / "000001-x.png")
    assert "120 x 100 pixels, the sensor has 640 x 512" in imp(c)
    assert "saturated" in imp(cap, "--saturated", "error")
    (tmp_path / "empty").mkdir()
    assert "manifest" in imp(tmp_path / "empty")
    assert "split" in imp(_edit_manifest(cap, tmp_path / "d", lambda r: [{**x, "split": "holdout"} for x in r]))
    # saturated samples dropped on request, and reported
    rc, out, err = _run(["dataset", "import", cap, "-o", tmp_path / "ok", "--calibration", cap / "flat.csv",
                         "--reference", ref, "--saturated", "drop", "--json"], capsys)
    rep = json.loads(out)
    assert rc == 0 and rep["samples"] == 4 and rep["saturated"] == 1 and rep["saturated_samples"] == ["000004"]


def test_synthetic_captures_are_seeded_and_16_bit(captures, tmp_path):
    """Same seed, same bytes; frames are uint16 with the dark offset, the over-exposed sample clips; through
    the nominal device the calibration recovers the relay to 0.1 px."""
    from metadesign.reconstruction.captures import import_captures, read_frame
    from metadesign.sensing.camera import Alignment, CameraSpec
    from metadesign.studies.captures import CaptureSession, synth_captures

    cam = CameraSpec(photons_at_peak=1e6, read_noise_e=2.0, hot_pixels=15)
    for name in ("c1", "c2"):
        synth_captures(captures["ref"], captures["ref"], tmp_path / name, Alignment(**TRUE), cam,
                       CaptureSession(samples=3, saturate=1, fmt="tiff", seed=2, flats=2, darks=1))
    a, full = read_frame(tmp_path / "c1" / "frames" / "000000-x.tif")
    b, _ = read_frame(tmp_path / "c2" / "frames" / "000000-x.tif")
    assert full == 65535 and np.array_equal(a, b)
    sat, _ = read_frame(tmp_path / "c1" / "frames" / "000002-x.tif")
    assert sat.max() == 65535 and a.max() < 65535
    d, _ = read_frame(tmp_path / "c1" / "dark" / "dark00.tif")
    assert abs(np.median(d) - cam.dark_counts) <= 2
    rep = import_captures(tmp_path / "c1", tmp_path / "imp", tmp_path / "c1" / "flat.csv", captures["ref"],
                          [tmp_path / "c1" / "dark" / "dark00.tif"])
    fitted, true = Alignment(**rep["calibration"]["alignment"]), Alignment(**TRUE)
    pts = np.array([[0, 0], [639, 0], [0, 511], [639, 511]], float)
    assert np.abs(fitted.forward(pts, (512, 640)) - true.forward(pts, (512, 640))).max() < 0.1



@pytest.mark.slow  # a training run: the default suite's 10-minute budget
def test_transfer_runs_three_models_on_the_imported_set_and_resumes(tmp_path, tiny_dataset, demo_products):
    """``metadesign transfer`` at toy scale: device as made, captures, import (the relay recovered), and the
    unadapted / fine-tuned / scratch models on the same imported test split (the phase conjugate through the
    SLM is 1); a re-run resumes every finished step."""
    from conftest import REPO, run_cli, tiny_model

    tiny_model(tmp_path)
    (tmp_path / "tr.toml").write_text(f"""[dataset]
layout = "{demo_products['layout']}"
sensor = "{REPO / 'sensing' / 'demo.toml'}"
turbulence = "{REPO / 'sensing' / 'turbulence.toml'}"
samples = 10
split = [0.6, 0.2, 0.2]
seed = 4
tensor_size = 16
shard_size = 5
[fabrication]
bias_x_nm = 10.0
bias_y_nm = -10.0
[captures]
reference = "{tiny_dataset}"
shift_px = [2.5, -1.5]
rotation_deg = 0.2
hot_pixels = 5
[evaluate]
model = "m.safetensors"
[finetune]
train = "t.toml"
epochs = 1
loss = "phase"
[scratch]
epochs = 2
pretrain_epochs = 1
""")
    r = run_cli("transfer", str(tmp_path / "tr.toml"), "-o", str(tmp_path / "out"), "-j", "1", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    rows = rep["rows"]
    assert set(rows) == {"unadapted", "finetuned", "scratch"}
    for v in rows.values():
        assert v["n"] == 2 and v["npib_phase_conjugate"] == pytest.approx(1.0, abs=1e-4)
        assert v["npib_none"] == pytest.approx(rows["unadapted"]["npib_none"], rel=1e-6)
    fit, true = rep["fitted_alignment"], rep["truth_alignment"]
    assert abs(fit["shift_x_px"] - true["shift_x_px"]) < 1 and abs(fit["shift_y_px"] - true["shift_y_px"]) < 1
    assert rows["finetuned"]["train_samples"] == 6
    assert (tmp_path / "out" / "transfer.png").stat().st_size > 0
    again = run_cli("transfer", str(tmp_path / "tr.toml"), "-o", str(tmp_path / "out"), "-j", "1", "--json")
    assert again.returncode == 0 and json.loads(again.stdout)["rows"] == rows


def _tree(folder) -> set:
    return {(str(p.relative_to(folder)), p.stat().st_size) for p in folder.rglob("*") if p.is_file()}


def test_import_never_deletes_what_it_did_not_write(captures, tmp_path, capsys):
    """--overwrite replaces only a metadesign dataset: a user's folder, or the captures themselves (an input
    is never its own output), survive byte for byte with one line and exit 2."""
    cap, ref = captures["cap"], captures["ref"]
    mine = tmp_path / "mine"
    (mine / ".ssh").mkdir(parents=True)
    (mine / ".ssh" / "id").write_text("key")
    (mine / "notes.txt").write_text("thesis")
    before = _tree(mine)
    rc, _, err = _run(["dataset", "import", cap, "-o", mine, "--calibration", cap / "flat.csv", "--reference", ref,
                       "--overwrite"], capsys)
    assert rc == 2 and len(err) == 1 and "not a metadesign dataset" in err[0], err
    assert _tree(mine) == before
    copy = tmp_path / "cap"
    shutil.copytree(cap, copy)
    before = _tree(copy)
    for out in (copy, copy / "frames", tmp_path):  # the captures, inside them, around them
        rc, _, err = _run(["dataset", "import", copy, "-o", out, "--calibration", copy / "flat.csv",
                           "--reference", ref, "--overwrite"], capsys)
        assert rc == 2 and len(err) == 1 and "overlaps the input" in err[0], err
        assert _tree(copy) == before
    # a dataset the project wrote is replaced
    ok = tmp_path / "ok"
    assert _run(["dataset", "import", cap, "-o", ok, "--calibration", cap / "flat.csv", "--reference", ref],
                capsys)[0] == 0
    assert _run(["dataset", "import", cap, "-o", ok, "--calibration", cap / "flat.csv", "--reference", ref,
                 "--overwrite"], capsys)[0] == 0


@pytest.mark.parametrize("value", ["inf", "-3", "nan", "12", "abc"])
def test_manifest_rytov_out_of_range_is_one_line(captures, tmp_path, capsys, value):
    cap, ref = captures["cap"], captures["ref"]
    src = _edit_manifest(cap, tmp_path / "m", lambda r: [{**x, "rytov": value if i == 1 else x["rytov"]}
                                                         for i, x in enumerate(r)])
    rc, _, err = _run(["dataset", "import", src, "-o", tmp_path / "out", "--calibration", cap / "flat.csv",
                       "--reference", ref], capsys)
    assert rc == 2 and len(err) == 1 and "rytov" in err[0], err
    assert not (tmp_path / "out").exists()


def test_missing_rytov_is_stored_and_reported_as_unknown(captures, tmp_path, capsys):
    cap, ref = captures["cap"], captures["ref"]
    src = _edit_manifest(cap, tmp_path / "m", lambda r: [{k: v for k, v in x.items() if k != "rytov"} for x in r])
    out = tmp_path / "out"
    assert _run(["dataset", "import", src, "-o", out, "--calibration", cap / "flat.csv", "--reference", ref],
                capsys)[0] == 0
    rc, text, _ = _run(["dataset", "show", out], capsys)
    assert rc == 0 and "Rytov          unknown" in text, text
    rc, js, _ = _run(["dataset", "show", out, "--json"], capsys)
    s = json.loads(js)
    assert s["rytov_nominal"] is None and s["rytov_unknown"] == s["samples"]
    from metadesign.reconstruction.evaluate import summarise

    r = {"none": np.full(3, 0.1), "unet": np.full(3, 0.3), "phase_conjugate": np.full(3, 0.5),
         "complex_conjugate": np.full(3, 0.6), "residual_rms": np.ones(3), "residual_tiptilt_rms": np.ones(3),
         "rytov_measured": np.full(3, np.nan)}
    assert list(summarise(r)["by_rytov"]) == ["unknown"]


def test_slm_phase_on_another_grid_needs_its_extent_and_is_resampled(captures, tmp_path, capsys):
    """A 4x finer SLM map of a tilt: refused without slm_extent_mm; with it, resampled onto the receiver crop
    it equals the tilt evaluated at the crop's own coordinates (the analytic answer)."""
    from metadesign.reconstruction.captures import _phase
    from metadesign.reconstruction.dataset import load_device

    cap, ref = captures["cap"], captures["ref"]
    crop = load_device(ref).crop
    m = 4 * crop.size + 3
    ext = 1.3 * crop.extent
    u = (np.arange(m) - (m - 1) / 2) * ext / m
    g = 2.0 / crop.aperture  # rad per metre: a gentle tilt (no wraps across a crop sample)
    tilt = (g * u)[None, :] + 0 * u[:, None]
    np.save(tmp_path / "fine.npy", tilt)
    got = _phase(tmp_path / "fine.npy", crop, 1.0, ext)
    want = (g * crop.coords())[None, :] + 0 * crop.coords()[:, None]
    assert np.abs(got - want).max() < 2e-3 * np.abs(want).max()
    with pytest.raises(Exception, match="slm_extent_mm"):
        _phase(tmp_path / "fine.npy", crop, 1.0)
    src = _edit_manifest(cap, tmp_path / "m", lambda r: [{**x, "slm_phase": str(tmp_path / "fine.npy")} for x in r])
    rc, _, err = _run(["dataset", "import", src, "-o", tmp_path / "out", "--calibration", cap / "flat.csv",
                       "--reference", ref], capsys)
    assert rc == 2 and len(err) == 1 and "slm_extent_mm" in err[0] and f"{crop.size} x {crop.size}" in err[0]
    src2 = _edit_manifest(cap, tmp_path / "m2", lambda r: [{**x, "slm_phase": str(tmp_path / "fine.npy"),
                                                            "slm_extent_mm": f"{ext * 1e3:.9g}"} for x in r])
    assert _run(["dataset", "import", src2, "-o", tmp_path / "out2", "--calibration", cap / "flat.csv",
                 "--reference", ref], capsys)[0] == 0


def test_synth_captures_refuses_an_empty_split(captures, tmp_path, capsys):
    ref = captures["ref"]
    from metadesign.reconstruction.dataset import open_dataset

    empty = next(s for s in ("train", "val", "test") if not len(open_dataset(ref).indices(s)))
    rc, _, err = _run(["dataset", "synth-captures", ref, "--device", ref, "--split", empty, "-o",
                       tmp_path / "c"], capsys)
    assert rc == 2 and len(err) == 1 and "empty" in err[0] and not (tmp_path / "c").exists()


def test_fits_frames_import_as_the_same_counts_in_png(captures, tmp_path, capsys):
    """The same synthetic captures written as FITS (unsigned 16-bit: BZERO 32768) and as PNG import to
    identical tensors; a FITS frame reads back as the uint16 counts written."""
    from astropy.io import fits

    from metadesign.reconstruction.captures import import_captures, read_frame
    from metadesign.sensing.camera import Alignment, CameraSpec
    from metadesign.studies.captures import CaptureSession, synth_captures

    cam = CameraSpec(photons_at_peak=1e6, read_noise_e=2.0, hot_pixels=15)
    cap = tmp_path / "cap-fits"
    synth_captures(captures["ref"], captures["device"], cap, Alignment(**TRUE), cam,
                   CaptureSession(samples=5, saturate=1, fmt="fits", seed=2))
    f = cap / "frames" / "000000-x.fits"
    raw = fits.getdata(f)
    a, full = read_frame(f)
    assert raw.dtype == np.uint16 and full == 65535 and np.array_equal(a, raw.astype(np.float64))
    png, _ = read_frame(captures["cap"] / "frames" / "000000-x.png")
    assert np.array_equal(a, png)
    got = {}
    for name, folder in (("fits", cap), ("png", captures["cap"])):
        import_captures(folder, tmp_path / name, folder / "flat.csv", captures["ref"], sorted((folder / "dark").glob("*")))
        from metadesign.reconstruction.data import PSFDataset

        ds = PSFDataset(tmp_path / name, "all")
        got[name] = np.stack([ds.get(j)["psf"] for j in range(len(ds))])
    assert np.array_equal(got["fits"], got["png"])
