"""The loop's hardware keys (issue #50): the mirror's stroke, measured influence functions and a separate
tip/tilt mirror, the detector's photon budget, and the Shack-Hartmann's lenslet count from the path's r0,
each against an independent reference (a least-squares plane, Poisson statistics, the closed-form r0 of a
uniform-Cn2 spherical wave)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import run_main

torch = pytest.importorskip("torch")
REPO = Path(__file__).resolve().parents[1]
TURBULENCE = REPO / "sensing" / "turbulence.toml"


def _crop():
    from metadesign.reconstruction.dataset import received_crop
    from metadesign.sensing.device import ReceiverCrop
    from metadesign.turbulence.scenario import load_scenario

    sc = load_scenario(TURBULENCE)
    return ReceiverCrop.of_scenario(sc, *received_crop(sc)), sc


def _recipe(tmp_path: Path, loop: str = "", dm: str = "") -> Path:
    p = tmp_path / "loop.toml"
    p.write_text(f'[device]\ndesign = "{REPO / "layouts" / "demo.toml"}"\nsensor = "{REPO / "sensing" / "demo.toml"}"\n'
                 f'turbulence = "{TURBULENCE}"\n[loop]\nmethods = ["ideal", "open"]\n{loop}[dm]\n{dm}'
                 "[wind]\nspeed_m_s = 3.0\n")
    return p


def _plane(phi, mask, x):
    """The least-squares tilt plane (no piston) of ``phi`` on ``mask`` (numpy lstsq on x, y, 1)."""
    X, Y = np.meshgrid(x, x)
    A = np.stack([X[mask], Y[mask], np.ones(mask.sum())], 1)
    coef = np.linalg.lstsq(A, phi[mask], rcond=None)[0]
    return coef[0] * X + coef[1] * Y


def test_a_tip_tilt_mirror_takes_the_tilt_and_the_mirror_the_rest():
    """A 20-rad tilt plus a 1-rad bump: the tip/tilt mirror's surface is the least-squares plane, the mirror's
    commands its fit of what the plane leaves; with a 0.5-rad stroke the mirror alone cannot follow the tilt."""
    from metadesign.optics.dm import DeformableMirror, TipTiltSplit

    crop, _ = _crop()
    x = np.asarray(crop.coords())
    X, Y = np.meshgrid(x, x)
    dm = DeformableMirror.for_crop(crop, n_act=8, coupling=0.15, stroke=0.5, regularisation=1e-4)
    mask = dm.mask
    tilt = 20.0 * X / crop.aperture - 7.0 * Y / crop.aperture
    bump = 0.4 * np.exp(-((X - 0.01) ** 2 + (Y + 0.015) ** 2) / (2 * 0.012 ** 2))
    phi = tilt + bump
    split = TipTiltSplit(dm)
    assert split.n == dm.n + 2
    c = split.fit(phi)
    plane = _plane(phi, mask, x)
    tt = split.tip_tilt.surface(c[:2])
    assert np.sqrt(np.mean((tt - plane)[mask] ** 2)) < 1e-3 * np.sqrt(np.mean(plane[mask] ** 2))
    np.testing.assert_allclose(c[2:], dm.fit(phi - plane), atol=2e-3)
    res = (phi - split.surface(c))[mask]
    alone = (phi - dm.surface(dm.fit(phi)))[mask]
    assert np.std(res) < 0.05 < 0.5 * np.std(alone)  # clipped at 0.5 rad, the mirror alone leaves the tilt
    assert np.abs(c[2:]).max() < 0.5  # the mirror's commands within its stroke, unclipped


def test_a_mirror_that_cannot_move_is_the_open_loop():
    """A stroke of 1e-9 rad: the ideal sensor's closed loop is the open loop (the mirror clips every command)."""
    from test_loop import _world

    from metadesign.optics.control import Controller
    from metadesign.optics.dm import DeformableMirror
    from metadesign.sensing.device import ReceiverCrop
    from metadesign.studies.loop import IdealPhaseSensor, LoopTiming, run_loop

    world = _world(8.0, 5)
    crop = ReceiverCrop.of_scenario(world.turbulence.sc, world.c0, world.a)
    stuck = DeformableMirror.for_crop(crop, n_act=8, stroke=1e-9, regularisation=1e-4)
    free = DeformableMirror.for_crop(crop, n_act=8, regularisation=1e-4)
    timing = LoopTiming(2000.0, substeps=2)
    open_ = run_loop(world, timing, 5, "open")
    closed = run_loop(world, timing, 5, "ideal", IdealPhaseSensor(), stuck, Controller(0.8, 1.0))
    moving = run_loop(world, timing, 5, "ideal", IdealPhaseSensor(), free, Controller(0.8, 1.0))
    np.testing.assert_allclose(closed["npib"], open_["npib"], rtol=1e-5)
    assert moving["npib"][2:].mean() > 1.2 * open_["npib"][2:].mean()


def test_the_recipe_mirror_converts_its_stroke_and_takes_measured_influence_functions(tmp_path):
    from metadesign.optics.dm import DeformableMirror, ModalDM, TipTiltSplit
    from metadesign.studies.loop_recipe import load_loop_recipe
    from metadesign.studies.loop_study import loop_mirror

    crop, sc = _crop()
    lam = 1550e-9  # the beacon's wavelength (sensing/turbulence.toml)
    gauss = DeformableMirror.for_crop(crop, n_act=12, coupling=0.15, regularisation=1e-3)
    np.save(tmp_path / "inf.npy", gauss.influence)
    rec = load_loop_recipe(_recipe(tmp_path, dm='stroke_um = 0.5\ninfluence = "inf.npy"\n'))
    assert rec.influence == tmp_path / "inf.npy" and rec.dm.stroke_m == pytest.approx(0.5e-6)
    m = loop_mirror(rec, crop, sc.wavelength)
    assert isinstance(m, DeformableMirror) and m.n == gauss.n and m.pitch is None  # measured, not the Gaussians
    assert m.stroke == pytest.approx(4 * np.pi * 0.5e-6 / lam)  # 4.054 rad
    phi = np.random.default_rng(0).normal(size=crop.size * crop.size).reshape(crop.size, crop.size)
    np.testing.assert_allclose(m.fit(phi), gauss.fit(phi), rtol=1e-4, atol=1e-5)
    rec = load_loop_recipe(_recipe(tmp_path, dm='kind = "modal"\nmodes = 6\nstroke_um = 1.0\ntip_tilt = true\n'))
    m = loop_mirror(rec, crop, sc.wavelength)
    assert isinstance(m, TipTiltSplit) and isinstance(m.mirror, ModalDM) and m.n == 8
    np.testing.assert_allclose(m.limits, [np.inf, np.inf] + [4 * np.pi * 1e-6 / lam] * 6, rtol=1e-6)
    default = loop_mirror(load_loop_recipe(_recipe(tmp_path)), crop, sc.wavelength)
    assert type(default) is DeformableMirror and default.n_act == 12 and not np.isfinite(default.stroke)


def test_the_photon_budget_is_the_detectors_photons_at_each_frames_peak(tmp_path):
    """A uniform frame read with ``photons_per_frame`` P and read noise r has the Poisson variance
    ``1/P + r^2/P^2`` (units of the peak); without photons the detector is the Gaussian one the loop had."""
    from metadesign.sensing.detector import Detector
    from metadesign.studies.loop_recipe import load_loop_recipe
    from metadesign.studies.loop_study import loop_detector

    default = loop_detector(load_loop_recipe(_recipe(tmp_path)))
    assert default == Detector.gaussian(5.0, 0)
    assert loop_detector(load_loop_recipe(_recipe(tmp_path, "noise_percent = 0.0\n"))) is None
    for P, r in ((400.0, 0.0), (400.0, 5.0)):
        det = loop_detector(load_loop_recipe(_recipe(tmp_path, f"noise_percent = 0.0\nphotons_per_frame = {P}\n"
                                                               f"read_noise_e = {r}\n")))
        x = det.read(np.ones((2, 128, 128), np.float32), np.random.default_rng(1))
        assert x.mean() == pytest.approx(1.0, abs=2e-3)
        assert x.var() == pytest.approx(1 / P + r * r / P / P, rel=0.03)


def test_the_shack_hartmann_frame_gets_the_same_photon_budget():
    """Its whole frame (every spot) read once: the noise power over the frame is the Poisson sum
    ``sum(clean / peak) / P`` plus ``N_pixels r^2 / P^2``."""
    from metadesign.reconstruction.shack_hartmann import ShackHartmann, SHConfig
    from metadesign.sensing.detector import Detector, NoiseSpec
    from metadesign.studies.loop_study import ShackHartmannLoopSensor

    crop, sc = _crop()
    sh = ShackHartmann.for_crop(SHConfig(lenslets=8), crop, sc.wavelength)
    u = sh.ap.astype(np.complex64)
    clean = sh.frames(u[None])
    peak = clean.max()
    for P, r in ((200.0, 0.0), (100.0, 3.0)):
        s = ShackHartmannLoopSensor(SimpleNamespace(sh=sh), Detector(NoiseSpec(photons_at_peak=P, read_noise_e=r)), 0)
        power = np.mean([np.sum((s.expose([u], k)["sh_spots"] - clean) ** 2) / peak ** 2 for k in range(12)])
        expected = np.sum(clean / peak) / P + clean.size * r * r / P / P
        assert power == pytest.approx(expected, rel=0.08), (P, r)


def test_auto_lenslets_follow_the_paths_r0_at_its_rytov_number():
    """``ceil(D / r0)`` with r0 the closed-form spherical-wave Fried parameter of a uniform-Cn2 path at the
    Rytov number (``sigma_chi^2 = 0.563 k^(7/6) Cn2 L^(11/6) B(11/6, 11/6)``, ``r0 = (0.423 k^2 Cn2 3 L / 8)^(-3/5)``),
    clipped at 4 received-field samples per lenslet (10 across this 40-sample aperture)."""
    from scipy.special import beta

    from metadesign.reconstruction.shack_hartmann import SHConfig
    from metadesign.studies.loop_study import sh_lenslets_for

    _, sc0 = _crop()
    D, dx, L = sc0.receiver_aperture, sc0.dx, sc0.length
    k = 2 * np.pi / sc0.wavelength
    top = int(np.floor(D / (4 * dx) + 1e-9))
    assert top == 10
    seen = []
    for rytov in (0.05, 0.2, 0.3, 0.5, 1.0, 2.0, 3.0):
        cn2 = rytov / (0.563 * k ** (7 / 6) * L ** (11 / 6) * beta(11 / 6, 11 / 6))
        r0 = (0.423 * k * k * cn2 * 3 * L / 8) ** (-3 / 5)
        ratio = D / r0
        assert abs(ratio - round(ratio)) > 0.05  # away from a step (the 13-screen path is within 1 %)
        got = sh_lenslets_for(replace(sc0, rytov=rytov), "auto")
        want = min(max(int(np.ceil(ratio)), 2), top)
        assert got["lenslets"] == want and got["rule"] == "auto", (rytov, ratio, got)
        assert got["r0_m"] == pytest.approx(r0, rel=0.015)
        assert got["d_over_r0"] <= 1.0 or want == top
        SHConfig(lenslets=got["lenslets"])
        seen.append(want)
    assert seen == [2, 3, 4, 5, 8, 10, 10]  # stronger turbulence, more lenslets, up to the samples' limit
    fixed = sh_lenslets_for(replace(sc0, rytov=0.5), 8)
    assert fixed["lenslets"] == 8 and fixed["rule"] == "recipe"


def test_a_loop_with_every_new_key_runs_and_reports_its_choices(tmp_path, capsys):
    """auto lenslets, photons and read noise, a measured stroke-limited mirror behind a tip/tilt mirror: the
    run completes and the report records the Shack-Hartmann's count and why (5 at Rytov 0.5: D/r0 = 4.9)."""
    from metadesign.optics.dm import DeformableMirror

    crop, _ = _crop()
    np.save(tmp_path / "inf.npy", DeformableMirror.for_crop(crop, n_act=8, coupling=0.15).influence)
    rec = _recipe(tmp_path, 'steps = 3\nsubsteps = 1\nsh_lenslets = "auto"\nphotons_per_frame = 1000.0\n'
                            'read_noise_e = 2.0\nlatency_ms = {shack_hartmann = 0.1}\n',
                  'influence = "inf.npy"\nstroke_um = 2.0\ntip_tilt = true\n')
    rec.write_text(rec.read_text().replace('methods = ["ideal", "open"]', 'methods = ["shack_hartmann", "ideal", "open"]'))
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "out"], capsys)
    assert rc == 0, err
    rep = json.loads((tmp_path / "out" / "loop.json").read_text())
    sh = rep["shack_hartmann"]
    assert sh["lenslets"] == 5 and sh["rule"] == "auto" and "ceil(D / r0)" in sh["why"] and sh["d_over_r0"] <= 1
    assert rep["loop"]["sh_lenslets"] == "auto" and rep["loop"]["photons_per_frame"] == 1000.0
    assert rep["dm"]["tip_tilt"] is True and rep["dm"]["stroke_m"] == pytest.approx(2e-6)
    assert len(rep["dm"]["influence_sha256"]) == 64
    for m in ("shack_hartmann", "ideal", "open"):
        assert 0 < rep["methods"][m]["npib_mean"] <= 1.5
    assert any("Shack-Hartmann: 5 lenslets" in e for e in err), err
