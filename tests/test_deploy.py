"""#32: a model file a lab can deploy from alone.  The ONNX export carries the contract that turns two raw
camera frames into the input (camera geometry, quadrant windows, orientation, steps, the flat-frame
calibration signature, #52) and the output into an SLM command; `examples/deploy_onnx.py`, with numpy,
onnxruntime and astropy only (no torch, no metadesign), reconstructs from FITS frames (checked against a
flat capture) and matches metadesign's own preprocessing and model to 1e-5 rad."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, run_main, tiny_model

pytest.importorskip("onnxruntime")
fits = pytest.importorskip("astropy.io.fits")


@pytest.fixture(scope="module")
def exported(tmp_path_factory, tiny_dataset):
    base = tmp_path_factory.mktemp("deploy")
    model = tiny_model(base)
    return base, model


def test_onnxruntime_alone_reconstructs_from_fits_frames(exported, tiny_dataset, capsys):
    import torch

    from metadesign.reconstruction.dataset import load_device, normalise_psf
    from metadesign.reconstruction.model import load_model
    from metadesign.sensing.forward import sensor_frames
    from metadesign.sensing.sensor import psf_tensor

    base, model = exported
    onnx_path = base / "m.onnx"
    rc, _, err = run_main(["export", model, "-o", onnx_path, "--dataset", tiny_dataset, "--json"], capsys)
    assert rc == 0, err
    dev = load_device(tiny_dataset)
    n = dev.pupil.G.shape[-1]
    yy, xx = np.mgrid[:n, :n] / n
    phi = 2.0 * np.sin(2 * np.pi * xx) * np.cos(3 * np.pi * yy)  # an aberrated beacon on the pupil grid
    frames = sensor_frames(dev.pupil, dev.sensor, (np.cos(phi) + 1j * np.sin(phi)).astype(np.complex64))
    flat = sensor_frames(dev.pupil, dev.sensor, None)
    for p, name in enumerate(("x", "y")):
        fits.PrimaryHDU(np.asarray(frames[p], np.float64)).writeto(base / f"f{name}.fits", overwrite=True)
        fits.PrimaryHDU(np.asarray(flat[p], np.float64)).writeto(base / f"l{name}.fits", overwrite=True)
    # metadesign's own path: frames -> tensor -> normalised -> the model
    x_ref, _ = normalise_psf(psf_tensor(frames, dev.sensor))
    net, _ = load_model(model)
    with torch.no_grad():
        ref = net(torch.from_numpy(np.asarray(x_ref, np.float32))[None])[0].numpy()
    # the example, in a process of its own: numpy, onnxruntime, astropy; neither torch nor metadesign
    code = ("import runpy, sys, json; sys.argv = ['deploy_onnx.py', sys.argv[1], sys.argv[2], sys.argv[3], '-o', "
            "sys.argv[4], '--flat', sys.argv[5], sys.argv[6]]; runpy.run_path(%r, run_name='__main__'); "
            "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'metadesign'})))"
            % str(REPO / "examples" / "deploy_onnx.py"))
    p = subprocess.run([sys.executable, "-c", code, str(onnx_path), str(base / "fx.fits"), str(base / "fy.fits"),
                        str(base / "phase.npy"), str(base / "lx.fits"), str(base / "ly.fits")],
                       capture_output=True, text=True, cwd=base, timeout=300)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout.strip().splitlines()[-1]) == []  # no torch, no metadesign
    got = np.load(base / "phase.npy")
    assert got.shape == ref.shape and np.abs(got - ref).max() < 1e-5, np.abs(got - ref).max()
    # the contract: everything the example used, and the orientation check it offers
    sys.path.insert(0, str(REPO / "examples"))
    try:
        import deploy_onnx
    finally:
        sys.path.pop(0)
    _, meta = deploy_onnx.load(str(onnx_path))
    cam = meta["metadesign.camera"]
    assert cam["frame_px"] == {"width": dev.sensor.width_px, "height": dev.sensor.height_px}
    assert meta["metadesign.wavelength_m"] == pytest.approx(dev.wavelength)
    assert meta["metadesign.device"]["layout_sha256"] and "unit" in meta["metadesign.training_noise"]
    x_ex = deploy_onnx.input_tensor([frames[0], frames[1]], cam)[0]
    np.testing.assert_allclose(x_ex, x_ref, rtol=1e-6, atol=1e-8)
    v = deploy_onnx.diagnose(flat, cam["calibration_signature"])  # the flat it was checked with: as it is
    assert v["problem"] is None and np.abs(v["shift_px"]).max() < 0.05 and v["scale"] == pytest.approx(1, abs=1e-3)


def test_a_bad_dataset_for_the_contract_is_one_line(exported, tmp_path, capsys):
    """export --dataset with a missing path, a file, or a folder that is no dataset: one line, exit 2, no file."""
    _, model = exported
    (tmp_path / "empty").mkdir()
    for bad in (tmp_path / "missing", REPO / "library" / "paper.npz", tmp_path / "empty"):
        rc, _, err = run_main(["export", model, "-o", tmp_path / "m.onnx", "--dataset", bad], capsys)
        assert rc == 2 and len(err) == 1 and "dataset" in err[0], err
        assert not (tmp_path / "m.onnx").exists()
