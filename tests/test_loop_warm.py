"""The warm-started loop methods (issue #50): ``retrieval``, the phase-diversity retrieval capped by a latency
budget, and ``refine_warm``, the learned refinement started from the previous frame.  The warm start's
arithmetic against the residual built from the turbulence and the mirror's surface (a perfect estimator on
standing turbulence: the start is the current residual), the budget's iteration count against a cost
measured on a known clock, the refinement's U-Net run on the first frame only, and one short loop of each
method through ``metadesign loop``."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import run_main
from loop_helpers import loop_world as _world

torch = pytest.importorskip("torch")
REPO = Path(__file__).resolve().parents[1]


def _misfit_rad(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """The largest difference of two phases on ``mask``, modulo 2 pi and a piston."""
    w = np.exp(1j * (a - b))[mask]
    return float(np.abs(np.angle(w * np.conj(w.mean()))).max())


def test_the_warm_start_of_a_perfect_estimator_on_standing_turbulence_is_the_residual():
    """A perfect estimator (the residual field's phase) in a closed loop on standing turbulence: each
    frame's warm start, the last estimate minus what the mirror moved since, equals the residual phase the
    sensor sees now, built here from the turbulence and the mirror's surface (angle(U exp(-i s_k))); the last
    estimate alone does not (the mirror moved)."""
    from metadesign.optics.control import Controller
    from metadesign.optics.dm import DeformableMirror
    from metadesign.sensing.device import ReceiverCrop
    from metadesign.studies.loop import LoopTiming, WarmStartSensor, phase_of, run_loop

    class Perfect(WarmStartSensor):
        def __init__(self):
            self.starts, self.surfaces, self.estimates = [], [], []

        def measure(self, crops, k, surface=None):
            self.surfaces.append(np.array(surface))
            est = super().measure(crops, k, surface)
            self.starts.append(self.last_start)
            return est

        def expose(self, crops, k):
            return np.mean(np.asarray(crops), axis=0)

        def reconstruct(self, frame, start=None):
            self.estimates.append(phase_of(frame))
            return self.estimates[-1]

    steps = 6
    world, timing = _world(0.0, steps), LoopTiming(2000.0, substeps=2)
    dm = DeformableMirror.for_crop(ReceiverCrop.of_scenario(world.turbulence.sc, world.c0, world.a), n_act=8,
                                   coupling=0.15, regularisation=1e-4)
    s = Perfect()
    run_loop(world, timing, steps, "ideal", s, dm, Controller(0.5, 1.0))
    mask = world.mask
    field = world.received(world.screens_at(0))  # standing: every instant's
    assert s.starts[0] is None and len(s.starts) == steps
    for k in range(1, steps):
        residual = np.angle(field * np.exp(-1j * s.surfaces[k]))
        moved = np.abs(s.surfaces[k] - s.surfaces[k - 1])[mask].max()
        assert moved > 0.05, moved  # the mirror moved: the correction matters
        assert _misfit_rad(s.starts[k], residual, mask) < 1e-4
        assert _misfit_rad(s.estimates[k - 1], residual, mask) > 0.05  # the last estimate alone is not it
    # a second run starts afresh
    s2 = Perfect()
    run_loop(world, timing, 2, "ideal", s2, dm, Controller(0.5, 1.0))
    assert s2.starts[0] is None


def test_the_budget_picks_the_count_the_measured_cost_implies():
    """The retrieval's cost measured on a clock that advances ``overhead + n per`` per call of ``n``
    iterations: the calibration recovers both and gives floor((budget - overhead) / per) iterations; a budget
    below one iteration gives one, flagged."""
    from metadesign.studies.loop import RetrievalLoopSensor, budget_iterations

    class Clocked(RetrievalLoopSensor):
        def __init__(self, overhead, per):
            self.device, self.overhead, self.per, self.now, self.iterations = (
                SimpleNamespace(crop=SimpleNamespace(size=5)), overhead, per, 0.0, 1)

        def clock(self):
            return self.now

        def solve(self, psf, start, iterations):
            self.now += self.overhead + iterations * self.per
            return np.zeros((5, 5))

    s = Clocked(0.7e-3, 0.3e-3)
    cal = s.calibrate({"psf": None}, 5e-3, clock=s.clock)
    assert cal["per_iteration_ms"] == pytest.approx(0.3) and cal["overhead_ms"] == pytest.approx(0.7)
    assert cal["iterations"] == s.iterations == 14 and not cal["exceeds_budget"]  # (5 - 0.7) / 0.3 = 14.3
    s = Clocked(4e-3, 2e-3)
    cal = s.calibrate({"psf": None}, 5e-3, clock=s.clock)
    assert cal["iterations"] == s.iterations == 1 and cal["exceeds_budget"] and "exceeds" in cal["why"]
    assert budget_iterations(1e-3 + 3 * 2e-4, 2e-4, 1e-3) == (3, False)  # exactly three fit
    assert budget_iterations(1e-3, 2e-4, 0.9e-3) == (1, True)


@pytest.fixture(scope="module")
def refiner_recipe(tmp_path_factory):
    """A small refiner (untrained, K = 2) on the loop's device at tensor 16 (the demo layout and sensor,
    sensing/turbulence.toml; its twin the device's), and a loop recipe naming it."""
    from metadesign.reconstruction.dataset import received_crop
    from metadesign.reconstruction.model import UNetConfig, build_unet, save_model
    from metadesign.reconstruction.refine import RefineConfig, build_refiner, save_refiner
    from metadesign.sensing.device import Device, ReceiverCrop
    from metadesign.studies import loop_study
    from metadesign.studies.loop_recipe import load_loop_recipe

    tmp = tmp_path_factory.mktemp("loop-warm")
    torch.manual_seed(0)
    unet = build_unet(UNetConfig(base=4, depth=2, input_size=16, aperture_size=41)).eval()
    save_model(unet, tmp / "u.safetensors", {"noise_percent": 0})
    rec = tmp / "loop.toml"
    rec.write_text(f'[device]\ndesign = "{REPO / "layouts" / "demo.toml"}"\nsensor = "{REPO / "sensing" / "demo.toml"}"\n'
                   f'turbulence = "{REPO / "sensing" / "turbulence.toml"}"\n[loop]\nmethods = ["open"]\n'
                   '[wind]\nspeed_m_s = 3.0\n')
    chain = loop_study._system(load_loop_recipe(rec), tmp / "work", 16)
    tb = chain.at(0.5)
    c0, a = received_crop(tb.sc)
    dev = Device(chain.pupil, chain.sensing.sensor, ReceiverCrop.of_scenario(tb.sc, c0, a))
    save_refiner(build_refiner(unet, RefineConfig(steps=2, width=4, features=4), dev), tmp / "r.safetensors",
                 tmp / "u.safetensors", {"noise_percent": 0})
    rec.write_text(rec.read_text().replace("[loop]", f'model = "{tmp / "r.safetensors"}"\n[loop]'))
    return rec, dev, tb


def test_the_warm_refinement_runs_its_unet_on_the_first_frame_only(refiner_recipe):
    """refine_warm: frame 0 is the refinement from the U-Net (the refine method's estimate); later frames
    start its steps from the warm start, the refiner's own trajectory from that start, without the U-Net."""
    from metadesign.reconstruction.estimators import make_estimator
    from metadesign.reconstruction.refine import load_refiner
    from metadesign.studies.loop import RefineWarmSensor

    rec, dev, tb = refiner_recipe
    refiner, _ = load_refiner(rec.read_text().split('model = "')[1].split('"')[0])
    calls = []
    refiner.unet.register_forward_hook(lambda *a: calls.append(1))
    s = RefineWarmSensor(dev, refiner, None, 0)
    a = dev.crop.size
    yy, xx = (np.mgrid[:a, :a] - a // 2) / a
    x = np.asarray(dev.crop.coords())
    inside = np.hypot(x[None, :], x[:, None]) <= dev.crop.aperture / 2
    crops = [(np.exp(1j * 2.0 * (xx ** 2 - yy ** 2)) * inside).astype(np.complex64)]  # astigmatism
    surfaces = [np.zeros((a, a)), 0.3 * xx, 0.5 * xx + 0.1 * yy]
    est = [s.measure(crops, k, surface=surfaces[k]) for k in range(3)]
    assert len(calls) == 1  # the U-Net ran for frame 0 only
    frame = s.expose(crops, 0)
    cold = make_estimator("refine", dev, refiner=refiner).estimate(frame)
    np.testing.assert_allclose(est[0], np.asarray(cold)[0], atol=1e-6)
    start = est[1] - (surfaces[2] - surfaces[1])
    with torch.no_grad():
        want = refiner.trajectory(torch.from_numpy(frame["psf"]), start=torch.from_numpy(start[None]).float())[-1]
    np.testing.assert_allclose(est[2], (want * refiner.mask).numpy()[0], atol=1e-5)
    assert np.abs(est[2] - np.asarray(cold)[0]).max() > 1e-3  # not the U-Net's start


def test_a_short_loop_of_each_warm_method_runs_and_reports_its_budget(refiner_recipe, tmp_path, capsys):
    """``metadesign loop`` with retrieval and refine_warm: the report records the retrieval's budget, its
    measured costs and the iterations they imply; each method's delay is its measured latency's."""
    from metadesign.studies.loop import budget_iterations

    rec, _, _ = refiner_recipe
    r = tmp_path / "loop.toml"
    r.write_text(rec.read_text().replace('methods = ["open"]', 'methods = ["retrieval", "refine_warm", "open"]\n'
                                         'steps = 4\nsubsteps = 1\nretrieval_budget_ms = 5.0'))
    rc, _, err = run_main(["loop", r, "-o", tmp_path / "out"], capsys)
    assert rc == 0, err
    rep = json.loads((tmp_path / "out" / "loop.json").read_text())
    cal = rep["retrieval"]
    n, over = budget_iterations(5e-3, cal["per_iteration_ms"] * 1e-3, cal["overhead_ms"] * 1e-3)
    assert cal["iterations"] == n >= 1 and cal["exceeds_budget"] == over and cal["budget_ms"] == 5.0
    assert any("retrieval: " in e and "iteration" in e for e in err), err
    for m in ("retrieval", "refine_warm"):
        mr = rep["methods"][m]
        assert mr["latency_ms"] > 0 and mr["delay_frames"] == pytest.approx(1 + mr["latency_ms"] * 1e-3 * 2000.0)
        assert 0 < mr["npib_mean"] <= 1.5
    assert rep["methods"]["refine_warm"]["label"] == "metasurface + warm refinement"
