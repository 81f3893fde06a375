"""The polarisation (mosaic) camera of issue #52 (metadesign.sensing.mosaic): the micro-polariser against Malus's law
and an explicit Jones-matrix partial polariser, the extinction-ratio limits, crosstalk's power balance, the demosaic
of a uniform polarised field (with the pattern's geometry), the forward model at ideal polarisers equal to today's
frames, the raw 12-bit reader, and the recipes' bad values (one line, exit 2)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from test_baselines import _smooth_field, synthetic_device

from metadesign.sensing.mosaic import (
    IMX250MZR_PATTERN,
    MosaicCamera,
    demosaic,
    interleave,
    pixel_crosstalk,
    polariser_intensity,
    stokes,
    unmix,
)


def _jones(theta_deg, T, er):
    """A partial polariser's Jones matrix: R(theta) diag(sqrt T, sqrt(T / ER)) R(-theta) (the textbook form)."""
    t = math.radians(theta_deg)
    R = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    return R @ np.diag([math.sqrt(T), math.sqrt(T / er) if math.isfinite(er) else 0.0]) @ R.T


def _through(E, theta, T=1.0, er=math.inf):
    """``(I_theta, ix, iy, cross)`` of a field ``E = (Ex, Ey)`` (complex) through the Jones matrix."""
    out = _jones(theta, T, er) @ E
    return float(np.sum(np.abs(out) ** 2)), abs(E[0]) ** 2, abs(E[1]) ** 2, float(np.real(E[0] * np.conj(E[1])))


def test_malus_law():
    """Linear light at alpha through an ideal polariser at theta: T cos^2(theta - alpha), every angle."""
    for alpha in (0.0, 20.0, 45.0, 90.0, 133.0):
        a = math.radians(alpha)
        ix, iy, cross = math.cos(a) ** 2, math.sin(a) ** 2, math.cos(a) * math.sin(a)
        for theta in np.arange(0.0, 180.0, 7.5):
            got = polariser_intensity(ix, iy, cross, theta, 0.8)
            assert got == pytest.approx(0.8 * math.cos(math.radians(theta) - a) ** 2, abs=1e-12)


def test_partial_polariser_matches_jones_matrix_and_its_limits():
    """Random coherent fields through the partial polariser equal the Jones-matrix reference; light along the pass
    axis passes T, across it T / ER; unpolarised light (no cross term) passes T (1 + 1/ER) / 2 of its power at any
    angle; ER -> inf is the ideal polariser."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        E = rng.normal(size=2) + 1j * rng.normal(size=2)
        theta, T, er = rng.uniform(0, 180), rng.uniform(0.3, 1), rng.choice([2.0, 30.0, 300.0, math.inf])
        ref, ix, iy, cross = _through(E, theta, T, er)
        assert polariser_intensity(ix, iy, cross, theta, T, er) == pytest.approx(ref, rel=1e-12)
    T, er = 0.9, 100.0
    assert polariser_intensity(1.0, 0.0, 0.0, 0.0, T, er) == pytest.approx(T)
    assert polariser_intensity(1.0, 0.0, 0.0, 90.0, T, er) == pytest.approx(T / er)
    assert polariser_intensity(0.0, 1.0, 0.0, 45.0, T, er) == pytest.approx(T * (1 + 1 / er) / 2)
    for theta in (0.0, 30.0, 45.0, 135.0):
        assert polariser_intensity(0.5, 0.5, 0.0, theta, T, er) == pytest.approx(T * (1 + 1 / er) / 2)
    assert polariser_intensity(0.3, 0.7, 0.1, 60.0, 1.0, 1e12) == pytest.approx(
        polariser_intensity(0.3, 0.7, 0.1, 60.0), rel=1e-9)


def test_crosstalk_conserves_power_and_shares_a_quarter_with_each_neighbour():
    rng = np.random.default_rng(1)
    raw = np.zeros((20, 24))
    raw[1:-1, 1:-1] = rng.uniform(0, 1, (18, 22))  # nothing at the edge: no light leaks off the array
    out = pixel_crosstalk(raw, 0.08)
    assert out.sum() == pytest.approx(raw.sum(), rel=1e-12)
    one = np.zeros((5, 5))
    one[2, 2] = 1.0
    d = pixel_crosstalk(one, 0.08)
    assert d[2, 2] == pytest.approx(0.92)
    for r, c in ((1, 2), (3, 2), (2, 1), (2, 3)):
        assert d[r, c] == pytest.approx(0.02)
    assert d.sum() == pytest.approx(1.0) and d[1, 1] == 0.0
    edge = np.zeros((4, 4))
    edge[0, 0] = 1.0
    assert pixel_crosstalk(edge, 0.08).sum() == pytest.approx(1.0 - 0.04)  # two of its neighbours are off the array


def test_demosaic_of_a_uniform_polarised_field():
    """A uniform field linearly polarised at alpha, through the IMX250MZR's pattern (0 degrees at the bottom right of
    each super-pixel) with ER 50 and T 0.7: the x and y frames are T (cos^2 + sin^2 / ER) and T (sin^2 + cos^2 /
    ER); the Stokes estimate from all four pixels equals them, S2 is T (1 - 1/ER) sin 2 alpha; unmixing gives cos^2
    and sin^2."""
    T, er, alpha = 0.7, 50.0, math.radians(30.0)
    E = np.array([math.cos(alpha), math.sin(alpha)], complex)
    imgs = {a: np.full((3, 4), _through(E, a, T, er)[0]) for a in (0, 45, 90, 135)}
    raw = interleave(imgs, IMX250MZR_PATTERN)
    assert raw.shape == (6, 8)
    assert raw[1, 1] == imgs[0][0, 0] and raw[0, 0] == imgs[90][0, 0] and raw[0, 1] == imgs[45][0, 0]
    c2, s2 = math.cos(alpha) ** 2, math.sin(alpha) ** 2
    f = demosaic(raw, IMX250MZR_PATTERN)
    np.testing.assert_allclose(f[0], T * (c2 + s2 / er), rtol=1e-12)
    np.testing.assert_allclose(f[1], T * (s2 + c2 / er), rtol=1e-12)
    np.testing.assert_allclose(demosaic(raw, IMX250MZR_PATTERN, use_diagonal=True), f, rtol=1e-12)
    s = stokes(*(imgs[a] for a in (0, 45, 90, 135)))
    np.testing.assert_allclose(s[2], T * (1 - 1 / er) * math.sin(2 * alpha), rtol=1e-12)
    x, y = unmix(f[0], f[1], T, er)
    np.testing.assert_allclose(x, c2, rtol=1e-12)
    np.testing.assert_allclose(y, s2, rtol=1e-12)


def _device(**cam):
    """The synthetic device of the baselines' tests behind a mosaic camera of ``cam``."""
    from metadesign.sensing.device import Device

    cp, sensor = synthetic_device(n=24)
    return Device(cp, sensor, camera=MosaicCamera(**cam)), cp, sensor


def test_ideal_mosaic_equals_todays_frames_exactly():
    """Ideal polarisers (ER inf, T 1), no crosstalk, the half-pitch mosaic (frames on the sensor's grid), each
    super-pixel sampled at its centre: the frames, the PSF tensor and the exposure are today's, bit for bit (so is a
    sensing recipe whose [camera] says so).  With the pixels' own centres (offsets) the x frame is today's renderer
    on the grid shifted to the 0 degree pixels."""
    from metadesign.sensing.device import Device
    from metadesign.sensing.forward import quadrant_fields
    from metadesign.sensing.model import sensing_from_dict
    from metadesign.sensing.sensor import quadrant_slices

    dev, cp, sensor = _device(offsets=False)
    today = Device(cp, sensor)
    e = _smooth_field((24, 24), np.random.default_rng(0), 2).astype(np.complex64)
    assert dev.frame_sensor == sensor
    np.testing.assert_array_equal(dev.frames(e), today.frames(e))
    np.testing.assert_array_equal(dev.psfs(e), today.psfs(e))
    np.testing.assert_array_equal(dev.render(e).psfs, today.render(e).psfs)
    np.testing.assert_array_equal(dev.expose([e, 0.5 * e]).frames, today.expose([e, 0.5 * e]).frames)
    rec = sensing_from_dict({"camera": {"kind": "mosaic", "offsets": False}})
    assert rec.camera == MosaicCamera(offsets=False)
    assert sensing_from_dict({}).camera is None and sensing_from_dict({"camera": {"kind": "ideal"}}).camera is None
    # the pixels' own centres: the 0 degree pixel is the super-pixel's bottom right, +p/2 along x and y
    shifted, _, _ = _device(offsets=True)
    q = sensor.pixel_pitch / 2 / sensor.magnification / 2
    X, Y = sensor.coords()
    ref = np.zeros((sensor.height_px, sensor.width_px), np.float32)
    for k in range(1, 5):
        r, c = quadrant_slices(sensor, k)
        ref[r, c] = quadrant_fields(cp, 0, X[c] + q, Y[r] + q, sensor.quadrant_centre(k), e) * sensor.focal_pitch**2
    np.testing.assert_allclose(shifted.frames(e)[0], ref, rtol=1e-6, atol=1e-7 * ref.max())
    assert np.abs(shifted.frames(e)[0] - today.frames(e)[0]).max() > 1e-2 * ref.max()  # the offsets matter


def test_mosaic_camera_composes_with_the_detector_and_keeps_power():
    """A real camera renders one raw mosaic that the one detector reads, then demosaics; the 2x coarser mosaic
    gives half-size frames; finite ER leaks the other polarisation into each frame; the twin refuses a mosaic."""
    from metadesign.sensing.detector import Detector
    from metadesign.validation import ValidationError

    e = _smooth_field((24, 24), np.random.default_rng(2), 2).astype(np.complex64)
    dev, _, sensor = _device(extinction_ratio=30.0, crosstalk=0.02, pixel_pitch=sensor_pitch(), use_diagonal=True)
    shot = dev.render(e, Detector.gaussian(5.0, seed=3))
    assert shot.raw.shape == (sensor.height_px, sensor.width_px) and shot.frames.shape == (2, 32, 32)
    assert shot.psfs.shape == (8, sensor.tensor_size, sensor.tensor_size)
    ideal, _, _ = _device(offsets=False)
    leaky, _, _ = _device(offsets=False, extinction_ratio=10.0)
    fi, fl = ideal.frames(e), leaky.frames(e)
    np.testing.assert_allclose(fl[0], fi[0] + fi[1] / 10, rtol=0, atol=1e-6 * fi.max())  # I_0 = I_x + I_y / ER
    np.testing.assert_allclose(fl[1], fi[1] + fi[0] / 10, rtol=0, atol=1e-6 * fi.max())
    with pytest.raises(ValidationError, match="twin"):
        dev.twin()


def sensor_pitch() -> float:
    return 15e-6  # the synthetic sensor's pixel: a mosaic of that pitch makes 2x coarser frames


def test_raw_12bit_round_trip(tmp_path):
    """Mono12p (2 pixels in 3 bytes) and little-endian 16-bit raw files, MSB-aligned 16-bit PNGs: written, read back
    to the same counts; a count above 12 bits, a wrong size and stray low bits are one line each."""
    from PIL import Image

    from metadesign.reconstruction.mosaic_frames import (
        MosaicLayout,
        demosaic_counts,
        pack_mono12p,
        read_raw,
        unpack_mono12p,
        write_raw,
    )
    from metadesign.validation import ValidationError

    rng = np.random.default_rng(4)
    counts = rng.integers(0, 4096, (6, 8)).astype(np.uint16)
    counts[0, 0], counts[0, 1] = 4095, 0
    assert pack_mono12p(np.array([0xABC, 0x123])) == bytes([0xBC, 0x3A, 0x12])  # GenICam's Mono12p, by hand
    np.testing.assert_array_equal(unpack_mono12p(pack_mono12p(counts), counts.size).reshape(6, 8), counts)
    for packing, msb in (("mono12p", False), ("uint16le", False), ("uint16le", True)):
        lay = MosaicLayout(MosaicCamera(), 8, 6, 12, packing, msb)
        write_raw(tmp_path / f"{packing}{msb}.raw", counts, lay)
        got, full = read_raw(tmp_path / f"{packing}{msb}.raw", lay)
        np.testing.assert_array_equal(got, counts)
        assert full == 4095
    png = tmp_path / "msb.png"
    Image.fromarray((counts << 4).astype(np.uint16)).save(png)
    lay = MosaicLayout(MosaicCamera(), 8, 6, 12, "uint16le", True)
    np.testing.assert_array_equal(read_raw(png, lay)[0], counts)
    f = demosaic_counts(counts, lay)
    np.testing.assert_array_equal(f[0], counts[1::2, 1::2])  # 0 degrees: the bottom right of the IMX250MZR's
    np.testing.assert_array_equal(f[1], counts[0::2, 0::2])
    Image.fromarray(counts.astype(np.uint16) * 16 + 1).save(tmp_path / "bits.png")
    with pytest.raises(ValidationError, match="low 4 bits"):
        read_raw(tmp_path / "bits.png", lay)
    Image.fromarray((counts + 4096).astype(np.uint16)).save(tmp_path / "over.png")
    with pytest.raises(ValidationError, match="outside"):
        read_raw(tmp_path / "over.png", MosaicLayout(MosaicCamera(), 8, 6, 12, "uint16le"))
    (tmp_path / "short.raw").write_bytes(b"\0" * 10)
    with pytest.raises(ValidationError, match="bytes"):
        read_raw(tmp_path / "short.raw", MosaicLayout(MosaicCamera(), 8, 6))


@pytest.mark.parametrize("section,key,value", [
    ("raw", "bit_depth", "17"), ("raw", "packing", '"mono10"'), ("raw", "width_px", "7"),
    ("camera", "extinction_ratio", "0.5"), ("camera", "extinction_ratio", "nan"),
    ("camera", "pattern", "[[0, 45], [90, 90]]"), ("camera", "crosstalk_percent", "60.0"),
    ("camera", "transmission", "0.0"), ("camera", "kind", '"ideal"')])
def test_bad_mosaic_recipe_is_one_line(tmp_path, section, key, value, capsys):
    """A bad value in the vendor recipe of `dataset import --mosaic`: one line naming the field, exit 2, nothing
    written."""
    from conftest import run_main

    rec = {"raw": {"width_px": "8", "height_px": "6", "bit_depth": "12"}, "camera": {"kind": '"mosaic"'}}
    rec[section][key] = value
    path = tmp_path / "cam.toml"
    path.write_text("".join(f"[{s}]\n" + "".join(f"{k} = {v}\n" for k, v in kv.items()) for s, kv in rec.items()))
    code, _, err = run_main(["dataset", "import", tmp_path / "none", "-o", tmp_path / "out", "--calibration",
                             tmp_path / "flat.csv", "--reference", tmp_path / "ref", "--mosaic", path], capsys)
    assert code == 2 and len(err) == 1, err
    assert f"{section}.{key}" in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("text,field", [
    ('[camera]\nkind = "mosaic"\nextinction_ratio = 0.5\n', "camera.extinction_ratio"),
    ('[camera]\nkind = "mosaic"\npixel_pitch_um = 7.0\n', "camera.pixel_pitch_um"),
    ('[camera]\nkind = "polarised"\n', "camera.kind"),
    ('[camera]\nkind = "mosaic"\nincident = "elliptic"\n', "camera.incident")])
def test_bad_camera_section_of_a_sensing_recipe(text, field):
    import tomllib

    from metadesign.sensing.model import sensing_from_dict
    from metadesign.validation import ConfigError

    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        sensing_from_dict(tomllib.loads(text))


def test_a_dataset_built_through_a_mosaic_camera(tiny_dataset, demo_products, tmp_path):
    """A sensing recipe with a [camera] section makes every sample one raw mosaic capture, demosaicked: the same
    beacons (seeds) as the ideal camera's dataset, other tensors (ER 10 leaks each polarisation into the other),
    another recipe hash, the camera in the provenance."""
    from conftest import REPO

    from metadesign.reconstruction.dataset import build_dataset, load_dataset_recipe
    from metadesign.reconstruction.dataset_store import open_dataset, open_store

    sensor = tmp_path / "sensor.toml"
    sensor.write_text((REPO / "sensing" / "demo.toml").read_text()
                      + '\n[camera]\nkind = "mosaic"\nextinction_ratio = 10.0\npixel_pitch_um = 15.0\n')
    rec = tmp_path / "cam.toml"
    rec.write_text(f"""[dataset]
layout = "{demo_products['layout']}"
sensor = "{sensor}"
turbulence = "{REPO / 'sensing' / 'turbulence.toml'}"
samples = 4
tensor_size = 16
shard_size = 4
seed = 5
""")
    build_dataset(load_dataset_recipe(rec), tmp_path / "ds", workers=1)
    cam, ideal = open_dataset(tmp_path / "ds"), open_dataset(tiny_dataset)
    assert cam.attrs["provenance"]["camera"]["extinction_ratio"] == 10.0
    assert "camera" not in ideal.attrs["provenance"] and cam.attrs["recipe_hash"] != ideal.attrs["recipe_hash"]
    np.testing.assert_array_equal(cam.seed[:4], ideal.seed[:4])
    a, b = open_store(tmp_path / "ds")["psf"][:4], open_store(tiny_dataset)["psf"][:4]
    assert np.all(np.isfinite(a)) and np.allclose(a.sum(axis=(1, 2, 3)), 8, rtol=1e-4)
    assert np.abs(a - b).max() > 0.01 * b.max()


_POLCAM = """[study]
dataset = "{ds}"
model = "{model}"
split = "train"
limit = 2
extinction_ratios = [0.0, 30.0]
pixel_pitch_um = [7.5]
"""
_END = "pixel_pitch_um = [7.5]\n"


@pytest.mark.parametrize("change,match", [
    (("extinction_ratios = [0.0, 30.0]", "extinction_ratios = [0.5]"), "study.extinction_ratios"),
    (("extinction_ratios = [0.0, 30.0]", "extinction_ratios = [nan]"), "study.extinction_ratios"),
    (("pixel_pitch_um = [7.5]", "pixel_pitch_um = [7.0]"), "camera.pixel_pitch_um"),
    (("limit = 2", "limit = 0"), "study.limit"),
    (("limit = 2", "limit = 2\ncolour = 1"), "study.colour"),
    ((_END, _END + '[[variant]]\nextinction_ratio = 30.0\n'), r"variant\[0\]\.label"),
    ((_END, _END + '[[variant]]\nlabel = "x"\nunmix = 3\n'), "camera.unmix"),
    ((_END, _END + '[camera]\ncrosstalk_percent = 50.0\n'), "camera.crosstalk_percent"),
    (('model = "', 'model = "missing-'), "missing-"),
])
def test_bad_polcam_recipe_is_one_line_and_writes_nothing(change, match, tiny_dataset, tmp_path, capsys):
    """`metadesign polcam`: a bad recipe value, a camera whose mosaic does not tile the sensor, a missing model:
    one line naming it, exit 2, no output folder."""
    from conftest import run_main, tiny_model

    model = tiny_model(tmp_path)
    rec = tmp_path / "p.toml"
    rec.write_text(_POLCAM.format(ds=tiny_dataset, model=model).replace(*change))
    code, _, err = run_main(["polcam", rec, "-o", tmp_path / "out"], capsys)
    assert code == 2 and len(err) == 1, err
    assert re.search(match, err[0]), err
    assert not (tmp_path / "out").exists()


def test_polcam_runs_on_a_tiny_dataset(tiny_dataset, tmp_path, capsys):
    """The study end to end on two samples: the ideal camera's row is the dataset's own tensors, the ideal mosaic
    without offsets (today's frames) scores exactly as it does, the report and figure are written."""
    import json

    from conftest import run_main, tiny_model

    model = tiny_model(tmp_path)
    rec = tmp_path / "p.toml"
    rec.write_text(_POLCAM.format(ds=tiny_dataset, model=model)
                   + '[[variant]]\nlabel = "today"\nextinction_ratio = 0.0\npixel_pitch_um = 7.5\noffsets = false\n')
    code, out, err = run_main(["polcam", rec, "-o", tmp_path / "out", "--json"], capsys)
    assert code == 0, err
    rep = json.loads(out)
    cams = rep["cameras"]
    assert set(cams) == {"ideal", "ER inf, 7.5 um", "ER 30, 7.5 um", "today"}
    assert cams["today"]["unet"]["captured_fraction"] == cams["ideal"]["unet"]["captured_fraction"]
    assert rep["ideal_render_check"] < 1e-5 and rep["retraining"]["run"] is False
    assert (tmp_path / "out" / "polcam.json").is_file() and (tmp_path / "out" / "polcam.png").is_file()


def test_the_committed_polcam_study_matches_its_recipe_and_model():
    """sensing/polcam-demo/polcam.json was made with the recipe and the refiner committed beside it (re-run
    `metadesign polcam sensing/polcam-demo.toml -o sensing/polcam-demo` when either changes), and its verdict is
    the one its own numbers give."""
    import json

    from conftest import REPO

    from metadesign.config import load_toml
    from metadesign.studies.polcam import verdict
    from metadesign.tasks import content_key, file_key

    doc = json.loads((REPO / "sensing" / "polcam-demo" / "polcam.json").read_text())
    mw = doc["made_with"]
    raw = load_toml(REPO / "sensing" / "polcam-demo.toml")
    assert mw["model"]["weights_sha256"] == file_key(REPO / "sensing" / raw["study"]["model"])
    assert mw["recipe"]["key"] == content_key(raw)
    assert doc["verdict"] == json.loads(json.dumps(verdict(doc["cameras"], doc["networks"], doc["tolerance"])))
    assert doc["retraining"]["run"] is False and doc["n"] == raw["study"]["limit"]


def test_raw_mosaic_captures_import_as_their_two_frames(tiny_dataset, tmp_path):
    """12-bit synthetic captures (flats, darks with hot pixels, samples) packed into raw Mono12p mosaics (x behind
    the 0 degree pixels, y behind the 90, their mean behind the diagonals) import through `--mosaic` to exactly the
    tensors, calibration and flags of the two-frame import (hot pixels repaired from pixels behind the same
    micro-polariser)."""
    import csv

    from metadesign.reconstruction.captures import (
        ImportOptions,
        import_captures,
        read_frame,
    )
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.mosaic_frames import load_mosaic_layout, write_raw
    from metadesign.sensing.camera import Alignment, CameraSpec
    from metadesign.studies.captures import CaptureSession, synth_captures

    cam = CameraSpec(peak_counts=3500, photons_at_peak=1e6, read_noise_e=2.0, dark_counts=100, hot_pixels=15,
                     hot_counts=600, bit_depth=12)
    cap = tmp_path / "cap"
    synth_captures(tiny_dataset, tiny_dataset, cap, Alignment(shift_x_px=2.0, rotation_deg=0.2), cam,
                   CaptureSession(samples=3, flats=2, darks=2, seed=2))
    rec = tmp_path / "cam.toml"
    rec.write_text('[raw]\nwidth_px = 1280\nheight_px = 1024\nbit_depth = 12\npacking = "mono12p"\n'
                   '[camera]\nkind = "mosaic"\npattern = [[90, 45], [135, 0]]\n')
    layout = load_mosaic_layout(rec)

    def raw_of(x, y, out):
        d = ((x.astype(np.int64) + y) // 2).astype(np.uint16)
        write_raw(out, interleave({0: x, 90: y, 45: d, 135: d}, IMX250MZR_PATTERN), layout)
        return out

    def frame(p):
        return read_frame(p)[0].astype(np.uint16)

    mos = tmp_path / "mos"
    (mos / "dark").mkdir(parents=True)
    for name in ("manifest.csv", "flat.csv"):
        with open(cap / name, newline="") as fh:
            rows = list(csv.DictReader(fh))
        out = []
        for j, r in enumerate(rows):
            raw = raw_of(frame(cap / r["frame_x"]), frame(cap / r["frame_y"]), mos / f"{name[:4]}{j}.raw")
            keep = {k: v for k, v in r.items() if k not in ("frame_x", "frame_y")}
            if "slm_phase" in keep:
                keep["slm_phase"] = str(cap / keep["slm_phase"])
            out.append({**keep, "frame_raw": raw.name})
        with open(mos / name, "w", newline="") as fh:
            w = csv.DictWriter(fh, list(out[0]))
            w.writeheader()
            w.writerows(out)
    darks = sorted((cap / "dark").glob("*"))
    raw_darks = [raw_of(frame(d), frame(d), mos / "dark" / f"{d.stem}.raw") for d in darks]
    two = import_captures(cap, tmp_path / "two", cap / "flat.csv", tiny_dataset, darks, ImportOptions(saturation=4095))
    one = import_captures(mos, tmp_path / "one", mos / "flat.csv", tiny_dataset, raw_darks, mosaic=rec)
    assert one["calibration"]["alignment"] == two["calibration"]["alignment"]
    assert one["calibration"]["hot_pixels"] == 4 * two["calibration"]["hot_pixels"] > 0
    assert one["saturated"] == two["saturated"]
    a, b = PSFDataset(tmp_path / "one", "all"), PSFDataset(tmp_path / "two", "all")
    np.testing.assert_array_equal(np.stack([a.get(j)["psf"] for j in range(len(a))]),
                                  np.stack([b.get(j)["psf"] for j in range(len(b))]))
