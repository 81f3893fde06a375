"""#52: a frame that cannot be plugged in wrong.  A flat-wavefront frame's calibration signature (each spot's
ensquared energies: the defocus ladder) tells a flipped, mirrored, rotated, transposed or polarisation-swapped
frame from the contract's; offsets and scales are measured; the stand-alone example refuses a flipped frame
in one line; the contract is complete with or without the dataset.

The device of the detection tests is an independent one: ideal Eq. 1 lenses with the paper's focal-length
ladder (Table S1) written straight onto a coarse pupil grid, imaged onto a half-size camera (fast)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO, run_main, tiny_model

from metadesign.sensing.detector import NoiseSpec, add_noise
from metadesign.sensing.device import Device, ReceiverCrop
from metadesign.sensing.forward import CoarsePupil
from metadesign.sensing.orientation import (
    ORIENTATIONS,
    correct_frames,
    diagnose,
    orient_frames,
    relative,
    signature,
    signature_record,
)
from metadesign.sensing.sensor import SensorSpec
from metadesign.validation import ValidationError

F_X = (48.8e-3, 49.2e-3, 49.6e-3, 50.0e-3)  # Table S1
F_Y = (50.4e-3, 50.8e-3, 51.2e-3, 51.6e-3)
OFFSETS = ((-240e-6, -192e-6), (240e-6, -192e-6), (-240e-6, 192e-6), (240e-6, 192e-6))


def ladder_pupil(n: int = 112, aperture: float = 5e-3, z: float = 50e-3, wavelength: float = 1550e-9,
                 focal=(F_X, F_Y)) -> CoarsePupil:
    """Each channel an ideal Eq. 1 lens of the ladder on one quarter of the blocks' power, demodulated by
    the Fresnel chirp (the coarse pupil's convention)."""
    k0 = 2 * np.pi / wavelength
    X = (np.arange(n) - (n - 1) / 2) * aperture / n
    xx, yy = np.meshgrid(X, X)
    G = np.empty((2, 4, n, n), np.complex64)
    for p, fs in enumerate(focal):
        for k, (f, (ox, oy)) in enumerate(zip(fs, OFFSETS)):
            lens = -k0 * (np.sqrt(f**2 + (xx - ox) ** 2 + (yy - oy) ** 2) - f)
            G[p, k] = 0.25 * np.exp(1j * (lens + k0 * (xx**2 + yy**2) / (2 * z)))
    block = 64
    return CoarsePupil(G, X, block, aperture / n / block, wavelength, z, 0)


#: a 320 x 256 camera of 15 um behind a 5x relay: the paper's focal-plane field at half the pixels
SENSOR = SensorSpec(320, 256, 15e-6, 5.0, 50e-3, 16)


@pytest.fixture(scope="module")
def flat():
    return Device(ladder_pupil(), SENSOR).frames().astype(np.float64)


@pytest.fixture(scope="module")
def record(flat):
    return signature_record(flat)


def _noisy(f, percent, seed=0):
    return add_noise(f, NoiseSpec(gaussian_sigma=percent / 100, seed=seed)) if percent else f


def test_the_orientations_form_a_group_and_correcting_undoes_them():
    x = np.arange(2 * 4 * 4).reshape(2, 4, 4)
    for n in ORIENTATIONS:
        np.testing.assert_array_equal(correct_frames(orient_frames(x, n), n), x)
        assert relative(n, n) == "identity"
    assert len({orient_frames(x, n).tobytes() for n in ORIENTATIONS}) == 16  # all distinct
    assert relative("flip-ud", "flip-lr") == "rot180"  # flip-ud frames corrected as flip-lr: both axes off


def test_the_ladder_orders_the_spots_by_their_defocus(flat):
    """The in-focus spot (x-pol QIV, f = z) holds the most light in the smallest square; the y-pol spots,
    ever further from focus from QI to QIV, hold ever less (the signature is the physics of defocus)."""
    sig = signature(flat)
    ee_small = sig[:, 3]  # log ensquared energy in the smallest square
    assert np.argmax(ee_small) == 3
    assert np.all(np.diff(ee_small[4:]) < 0)
    defocus = np.abs(np.r_[F_X, F_Y] - 50e-3)
    assert np.corrcoef(defocus, sig[:, 2])[0, 1] > 0.9  # spot size grows with the defocus


@pytest.mark.parametrize("noise", [0, 10])
@pytest.mark.parametrize("turn", ["flip-ud", "flip-lr", "rot180", "transpose", "swap-pol", "swap-pol+flip-ud",
                                  "swap-pol+flip-lr", "swap-pol+rot180"])
def test_each_misorientation_is_refused_by_name_and_corrected_when_declared(flat, record, turn, noise):
    g = _noisy(orient_frames(flat, turn), noise, seed=3)
    v = diagnose(g, record)
    assert v.best == turn and v.problem() is not None, v
    assert f"--orientation {turn}" in v.problem() and "\n" not in v.problem()
    d = diagnose(g, record, declared=turn)
    assert d.problem() is None, d


def test_the_messages_say_what_is_wrong(flat, record):
    assert "flipped up-down" in diagnose(orient_frames(flat, "flip-ud"), record).problem()
    assert "rotated by 180 degrees" in diagnose(orient_frames(flat, "rot180"), record).problem()
    assert "polarisation frames are swapped" in diagnose(orient_frames(flat, "swap-pol"), record).problem()
    wrong = diagnose(orient_frames(flat, "rot180"), record, declared="flip-ud").problem()
    assert "declared flip-ud" in wrong and "--orientation rot180" in wrong
    other = Device(ladder_pupil(z=45e-3), SENSOR).frames()  # every spot defocused by 5 mm: not this device
    assert "does not match" in diagnose(other, record).problem()


@pytest.mark.parametrize("noise", [0, 5, 10])
def test_a_correct_frame_is_never_refused(flat, record, noise):
    for seed in range(2 if noise else 1):
        v = diagnose(_noisy(flat, noise, seed), record)
        assert v.problem() is None and v.best == "identity", v
        assert v.aligned


@pytest.mark.parametrize("dx,dy", [(2, 0), (0, -4), (8, 4)])
def test_an_offset_frame_is_measured(flat, record, dx, dy):
    g = np.roll(flat, (dy, dx), axis=(-2, -1))
    v = diagnose(_noisy(g, 5), record)
    assert v.problem() is None and not v.aligned
    assert np.hypot(v.shift_px[0] - dx, v.shift_px[1] - dy) < 0.5, v.shift_px


@pytest.mark.parametrize("s", [0.95, 1.05])
def test_a_scaled_frame_is_measured(flat, record, s):
    from scipy.ndimage import affine_transform

    c = np.array([(SENSOR.height_px - 1) / 2, (SENSOR.width_px - 1) / 2])
    g = np.stack([affine_transform(f, np.eye(2) / s, offset=c - c / s, order=1) / s**2 for f in flat])
    v = diagnose(g, record)
    assert v.problem() is None and abs(v.scale - s) < 0.005, v


def test_a_device_without_a_ladder_says_it_cannot_tell(flat):
    """Every channel focused alike (no diversity): the signature is the same flipped, and says so, rather than
    refusing good frames or pretending to check."""
    sym = Device(ladder_pupil(focal=((50e-3,) * 4,) * 2), SENSOR).frames()  # every lens focused on the camera
    rec = signature_record(sym)
    assert "rot180" in rec["symmetric"] and "swap-pol" in rec["symmetric"]
    v = diagnose(orient_frames(sym, "rot180"), rec)
    assert v.problem() is None and "cannot tell" in v.note()


def test_the_example_kernel_is_metadesigns(flat, record):
    sys.path.insert(0, str(REPO / "examples"))
    try:
        import deploy_onnx
    finally:
        sys.path.pop(0)
    g = _noisy(orient_frames(flat, "swap-pol+flip-lr"), 5, seed=1)
    prm = {k: record[k] for k in ("smooth_px", "threshold", "boxes_px")}
    np.testing.assert_array_equal(deploy_onnx.signature(g, prm), signature(g, prm))
    ours, theirs = diagnose(g, record), deploy_onnx.diagnose(g, record)
    assert (theirs["best"], theirs["problem"]) == (ours.best, ours.problem())
    d = diagnose(np.roll(flat, 3, axis=-1), record)
    t = deploy_onnx.diagnose(np.roll(flat, 3, axis=-1), record)
    assert np.allclose(t["shift_px"], d.shift_px) and t["scale"] == pytest.approx(d.scale)


def test_import_check_refuses_a_flipped_flat_and_puts_back_a_declared_one(flat):
    from metadesign.reconstruction.frame_orientation import (
        check_flat,
        check_orientation_record,
    )

    with pytest.raises(ValidationError, match="flat.csv: frame orientation: it is flipped up-down"):
        check_flat(orient_frames(flat, "flip-ud"), flat, "identity", "flat.csv")
    back, v = check_flat(orient_frames(flat, "flip-ud"), flat, "flip-ud", "flat.csv")
    np.testing.assert_array_equal(back, flat)
    with pytest.raises(ValidationError, match="--orientation: expected one of"):
        check_flat(flat, flat, "upside-down", "flat.csv")
    check_orientation_record({"propagation": "slm", "provenance": {"orientation": v.to_dict()}}, "ds")
    with pytest.raises(ValidationError, match="without the orientation check"):
        check_orientation_record({"propagation": "slm", "provenance": {}}, "ds")
    check_orientation_record({"provenance": {}}, "ds")  # a synthetic dataset


def test_a_bad_orientation_is_one_line(tmp_path, tiny_dataset, capsys):
    rc, _, err = run_main(["dataset", "import", tmp_path, "-o", tmp_path / "imp", "--calibration", tmp_path / "f.csv",
                           "--reference", tiny_dataset, "--orientation", "upside-down"], capsys)
    assert rc == 2 and len(err) == 1 and "--orientation" in err[0], err
    assert not (tmp_path / "imp").exists()


# ------------------------------------------------------------------------------------------ the contract


def _card(model, **extra):
    p = model.with_name(model.name + ".json")
    card = json.loads(p.read_text())
    card.update(extra)
    p.write_text(json.dumps(card))


@pytest.fixture(scope="module")
def carded(tmp_path_factory, tiny_dataset):
    """A copy of the tiny dataset with its recipe beside it (``ds.toml``, as committed recipes sit beside
    their datasets), and a model whose card names it."""
    from metadesign.reconstruction.dataset_store import open_dataset

    base = tmp_path_factory.mktemp("contract")
    ds = base / "ds"
    shutil.copytree(tiny_dataset, ds)
    shutil.copy(tiny_dataset.parent / "tiny.toml", base / "ds.toml")
    attrs = open_dataset(ds).attrs
    model = tiny_model(base)
    _card(model, dataset={"path": str(ds), "recipe_hash": attrs["recipe_hash"],
                          "layout_sha256": attrs["provenance"]["layout_sha256"]})
    return base, ds, model


def _meta(path):
    import onnxruntime as ort

    out = {}
    for k, v in ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).get_modelmeta() \
            .custom_metadata_map.items():
        try:
            out[k] = json.loads(v)
        except ValueError:
            out[k] = v
    return out


def test_a_contract_without_the_dataset_equals_one_with_it(carded, capsys):
    pytest.importorskip("onnxruntime")
    base, ds, model = carded
    rc, _, err = run_main(["export", model, "-o", base / "with.onnx", "--dataset", ds], capsys)
    assert rc == 0, err
    rc, out, err = run_main(["export", model, "-o", base / "without.onnx", "--json"], capsys)
    assert rc == 0, err
    assert json.loads(out)["device_source"].startswith("recipe")
    a, b = _meta(base / "with.onnx"), _meta(base / "without.onnx")
    assert a == b
    cam = a["metadesign.camera"]
    for key in ("frame_px", "pixel_pitch_m", "relay_magnification", "orientation", "channel_optics",
                "calibration_signature"):
        assert key in cam
    assert cam["relay_magnification"] > 0 and a["metadesign.wavelength_m"] == pytest.approx(1550e-9)
    assert [c["polarisation"] for c in cam["channel_optics"]] == list("xxxxyyyy")
    assert a["metadesign.device"]["layout_sha256"] and a["metadesign.device"]["dataset_recipe_hash"]


def test_without_its_layout_the_device_comes_from_the_design_recipe(tmp_path, demo_products):
    """A fresh checkout has no built layout: the device is designed from the recipe's design in a scratch
    folder, and the contract is the one the dataset gives."""
    from metadesign.reconstruction.contract_device import contract_device
    from metadesign.reconstruction.dataset import build_dataset, load_dataset_recipe
    from metadesign.reconstruction.dataset_store import open_dataset
    from metadesign.reconstruction.export import contract
    from metadesign.reconstruction.refine import load_network

    (tmp_path / "lay").mkdir()
    shutil.copy(demo_products["layout"], tmp_path / "lay" / "layout.oas")
    (tmp_path / "ds.toml").write_text(
        f'[dataset]\nlayout = "{tmp_path / "lay" / "layout.oas"}"\ndesign = "{REPO / "layouts" / "demo.toml"}"\n'
        f'sensor = "{REPO / "sensing" / "demo.toml"}"\nturbulence = "{REPO / "sensing" / "turbulence.toml"}"\n'
        "samples = 4\ntensor_size = 16\nshard_size = 4\nseed = 5\n")
    build_dataset(load_dataset_recipe(tmp_path / "ds.toml"), tmp_path / "ds", workers=1)
    attrs = open_dataset(tmp_path / "ds").attrs
    model = tiny_model(tmp_path)
    _card(model, dataset={"path": str(tmp_path / "ds"), "recipe_hash": attrs["recipe_hash"],
                          "layout_sha256": attrs["provenance"]["layout_sha256"]})
    net, card = load_network(model)
    want = contract(net, card, contract_device(model, card, tmp_path / "ds"))
    (tmp_path / "lay" / "layout.oas").unlink()
    cd = contract_device(model, card)
    assert "design" in cd.source and contract(net, card, cd) == want


def test_export_refuses_a_dataset_or_recipe_the_card_does_not_name(carded, tmp_path, capsys):
    _, ds, model = carded
    other = tmp_path / "m.safetensors"
    shutil.copy(model, other)
    shutil.copy(model.with_name(model.name + ".json"), tmp_path / "m.safetensors.json")
    _card(other, dataset={"path": str(ds), "recipe_hash": "0" * 64, "layout_sha256": "1" * 64})
    rc, _, err = run_main(["export", other, "-o", tmp_path / "a.onnx", "--dataset", ds], capsys)
    assert rc == 2 and len(err) == 1 and "layout differs" in err[0], err
    _card(other, dataset={"path": str(ds), "recipe_hash": "0" * 64})
    for argv in (["--dataset", ds], []):
        rc, _, err = run_main(["export", other, "-o", tmp_path / "a.onnx", *argv], capsys)
        assert rc == 2 and len(err) == 1 and "recipe differs" in err[0], err
    _card(other, dataset={})
    rc, _, err = run_main(["export", other, "-o", tmp_path / "a.onnx"], capsys)
    assert rc == 2 and len(err) == 1 and "names no dataset" in err[0], err
    assert not (tmp_path / "a.onnx").exists()


def test_a_co_designed_contract_names_its_device_and_diversity(carded):
    """The card's diversity at the device's own focal lengths and no Zernike terms is the device as built (its
    pupil unchanged); a learned one is named with its focal lengths per channel; the committed co-design
    card finds the committed design recipe that lays its device out."""
    from metadesign.reconstruction.contract_device import (
        _codesign_recipe,
        codesigned_pupil,
        contract_device,
    )
    from metadesign.reconstruction.export import camera_contract

    _, ds, model = carded
    card = json.loads(model.with_name(model.name + ".json").read_text())
    cd = contract_device(model, card, ds)
    f0 = (cd.lenses[..., 0] * 1e3).tolist()
    zero = {"focal_length_mm": f0, "zernike_noll": [5], "zernike_rad": np.zeros((2, 4, 1)).tolist()}
    p = codesigned_pupil(cd.device.pupil, cd.device.sensor, cd.lenses, zero)
    np.testing.assert_allclose(p.G, cd.device.pupil.G, atol=1e-6)
    f = (np.asarray(f0) * np.array([[1.001], [0.999]])).tolist()
    div = {"focal_length_mm": f, "zernike_noll": [5], "zernike_rad": np.full((2, 4, 1), 0.1).tolist()}
    co = contract_device(model, {**card, "codesign": div}, ds)
    assert co.identity["co_designed"] and co.identity["diversity"]["focal_length_mm"] == f
    assert co.identity["base_device"]["layout_sha256"] == cd.identity["layout_sha256"]
    optics = camera_contract(co)["channel_optics"]
    assert [o["focal_length_m"] for o in optics] == pytest.approx(np.ravel(f) * 1e-3)
    committed = json.loads((REPO / "sensing" / "models" / "codesign-demo-unet.safetensors.json").read_text())
    assert _codesign_recipe(committed["codesign"]).name == "codesign-demo.toml"


# ------------------------------------------------------------------------------ the stand-alone example


@pytest.fixture(scope="module")
def ladder_onnx(tmp_path_factory, carded):
    """An export whose contract is the ladder device on the small camera (the tiny model takes its 16^2
    tensors): what a lab gets for a device with a defocus ladder."""
    pytest.importorskip("onnxruntime")
    from metadesign.reconstruction import export as ex
    from metadesign.reconstruction.contract_device import ContractDevice

    _, _, model = carded
    pupil = ladder_pupil()
    lenses = np.array([[[f, *o] for f, o in zip(fs, OFFSETS)] for fs in (F_X, F_Y)])
    cd = ContractDevice(Device(pupil, SENSOR, ReceiverCrop(108, 41, 256, 0.0025, 0.1)),
                        {"design": "ideal ladder"}, lenses, source="test")
    mp = pytest.MonkeyPatch()
    mp.setattr(ex, "contract_device", lambda *a, **k: cd)
    try:
        out = tmp_path_factory.mktemp("ladder") / "m.onnx"
        ex.export_onnx(model, out)
    finally:
        mp.undo()
    return out, pupil


def _example(args, cwd):
    script = str(REPO / "examples" / "deploy_onnx.py")
    code = ("import runpy, sys, json; sys.argv = ['deploy_onnx.py'] + sys.argv[1:]; "
            f"runpy.run_path({script!r}, run_name='__main__'); "
            "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'metadesign'})))")
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          timeout=300, check=False)


def test_the_example_refuses_a_flipped_frame_in_one_line(ladder_onnx, tmp_path):
    fits = pytest.importorskip("astropy.io.fits")
    onnx_path, pupil = ladder_onnx
    n = pupil.G.shape[-1]
    yy, xx = np.mgrid[:n, :n] / n
    phi = 1.5 * np.sin(2 * np.pi * xx) * np.cos(np.pi * yy)
    frames = Device(pupil, SENSOR).frames((np.cos(phi) + 1j * np.sin(phi)).astype(np.complex64))
    flat = Device(pupil, SENSOR).frames()
    for name, f in (("f", frames), ("l", flat)):
        g = orient_frames(f, "flip-ud")
        for p in range(2):
            fits.PrimaryHDU(np.asarray(g[p], np.float64)).writeto(tmp_path / f"{name}{'xy'[p]}.fits")
    args = [onnx_path, tmp_path / "fx.fits", tmp_path / "fy.fits", "--flat", tmp_path / "lx.fits",
            tmp_path / "ly.fits", "-o", tmp_path / "phase.npy"]
    p = _example(args, tmp_path)
    lines = [x for x in p.stderr.splitlines() if x.strip()]
    assert p.returncode != 0 and len(lines) == 1, p.stderr
    assert lines[0] == ("flat frame: frame orientation: it is flipped up-down (a relay that inverts the rows?): "
                        "pass --orientation flip-ud")
    assert not (tmp_path / "phase.npy").exists()
    p = _example([*args, "--orientation", "flip-ud"], tmp_path)  # declared: put back, and the same phase
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout.strip().splitlines()[-1]) == []  # neither torch nor metadesign
    sys.path.insert(0, str(REPO / "examples"))
    try:
        import deploy_onnx
    finally:
        sys.path.pop(0)
    want, _ = deploy_onnx.reconstruct(str(onnx_path), list(frames), list(flat))
    np.testing.assert_allclose(np.load(tmp_path / "phase.npy"), want, atol=1e-5)
