"""The loop in time (issue #50) on a small path: a zero-gain loop is the open loop, a perfect sensor with the
loop's shortest delay on standing turbulence converges to the zero-delay mirror-fitted oracle, the same seed
gives the same bytes, and the loop recipe's bad values are one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import run_main
from loop_helpers import loop_numbers as _numbers
from loop_helpers import loop_world as _world

torch = pytest.importorskip("torch")
REPO = Path(__file__).resolve().parents[1]


def _dm(world):
    from metadesign.optics.dm import DeformableMirror
    from metadesign.sensing.device import ReceiverCrop

    crop = ReceiverCrop.of_scenario(world.turbulence.sc, world.c0, world.a)
    return DeformableMirror.for_crop(crop, n_act=8, coupling=0.15, regularisation=1e-4)


def test_a_zero_gain_loop_is_the_open_loop_and_the_same_seed_the_same_bytes():
    from metadesign.optics.control import Controller
    from metadesign.studies.loop import IdealPhaseSensor, LoopTiming, run_loop

    world, steps = _world(8.0, 6), 6
    timing = LoopTiming(2000.0, substeps=2)
    open_ = run_loop(world, timing, steps, "open")
    zero = run_loop(world, timing, steps, "ideal", IdealPhaseSensor(), _dm(world), Controller(0.0, 1.0))
    np.testing.assert_array_equal(zero["npib"], open_["npib"])
    again = run_loop(_world(8.0, 6), timing, steps, "open")
    np.testing.assert_array_equal(again["npib"], open_["npib"])
    assert (open_["npib"] > 0).all() and np.isfinite(open_["residual_rms"]).all()


def test_a_perfect_sensor_on_standing_turbulence_converges_to_the_fitted_oracle():
    """No wind, the ideal sensor, gain 1 and the shortest delay: the loop iterates the fit of its residual,
    frame after frame, to the zero-delay oracle's fixed point on the same (standing) phase."""
    from metadesign.optics.control import Controller
    from metadesign.studies.loop import IdealPhaseSensor, LoopTiming, run_loop

    world, steps = _world(0.0, 12), 12
    timing = LoopTiming(2000.0, substeps=2)
    dm = _dm(world)
    oracle = run_loop(world, timing, steps, "fitted", dm=dm)
    closed = run_loop(world, timing, steps, "ideal", IdealPhaseSensor(), dm, Controller(1.0, 1.0))
    open_ = run_loop(world, timing, steps, "open")
    assert closed["npib"][0] == pytest.approx(open_["npib"][0])  # nothing applied yet
    np.testing.assert_allclose(closed["npib"][8:], oracle["npib"][8:], rtol=0.01)
    assert oracle["npib"].mean() > 1.5 * open_["npib"].mean()


def test_the_loop_delay_follows_its_parts():
    from metadesign.studies.loop import LoopTiming

    t = LoopTiming(2000.0, substeps=4, readout_frames=0.5, latency_s=1e-3, dm_frames=0.25)
    assert t.delay_frames == pytest.approx(1 + 0.5 + 2.0 + 0.25)
    assert list(t.sub_steps(3)) == [12, 13, 14, 15]
    with pytest.raises(ValueError):
        LoopTiming(0.0)


def _recipe(tmp_path: Path, loop: str = "", wind: str = "speed_m_s = 3.0\n") -> Path:
    p = tmp_path / "loop.toml"
    p.write_text(f'[device]\ndesign = "{REPO / "layouts" / "demo.toml"}"\nsensor = "{REPO / "sensing" / "demo.toml"}"\n'
                 f'turbulence = "{REPO / "sensing" / "turbulence.toml"}"\n[loop]\nmethods = ["ideal", "open"]\n'
                 f"{loop}[wind]\n{wind}")
    return p


@pytest.mark.parametrize("loop, wind, match", [
    ("rate_hz = nan\n", "speed_m_s = 3.0\n", "loop.rate_hz"),
    ("gain = -1\n", "speed_m_s = 3.0\n", "loop.gain"),
    ('methods = ["ideal", "psychic"]\n', "speed_m_s = 3.0\n", "loop.methods"),
    ('methods = ["unet"]\n', "speed_m_s = 3.0\n", "device.model"),
    ('methods = ["realtime"]\n', "speed_m_s = 3.0\n", "device.realtime"),
    ("latency_ms = {ideal = -2}\n", "speed_m_s = 3.0\n", "loop.latency_ms"),
    ("", "speed_m_s = -3.0\n", "wind.speed_m_s"),
    ("", "speed_m_s = inf\n", "wind.speed_m_s"),
    ("", 'speed_m_s = 3.0\n[dm]\nkind = "magic"\n', "dm.kind"),
    ("", "speed_m_s = 3.0\n[dm]\nkind = \"modal\"\nmodes = 1\n", "dm.modes"),
])
def test_bad_loop_recipes_are_one_line_and_write_nothing(loop, wind, match, tmp_path, capsys):
    rec = _recipe(tmp_path, loop.replace('methods = ["ideal", "open"]\n', ""), wind)
    text = rec.read_text()
    if "methods" in loop:  # the bad list replaces the good one
        text = text.replace('methods = ["ideal", "open"]\n', "")
        rec.write_text(text)
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "out"], capsys)
    assert rc == 2 and len(err) == 1 and match in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("loop, match", [
    ('gain = "fast"\n', "loop.gain"),
    ("gain = nan\n", "loop.gain"),
    ("gain = 2.5\n", "loop.gain"),
    ("seeds = 0\n", "loop.seeds"),
    ("seeds = 1.5\n", "loop.seeds"),
    ("gain_steps = 1\n", "loop.gain_steps"),
    ('gain = "optimise"\nsteps = 50\ngain_steps = 60\n', "loop.gain_steps"),
    ('pseudo_open_loop = "yes"\n', "loop.pseudo_open_loop"),
])
def test_bad_new_loop_keys_are_one_line_and_write_nothing(loop, match, tmp_path, capsys):
    rec = _recipe(tmp_path, loop)
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "out"], capsys)
    assert rc == 2 and len(err) == 1 and match in err[0], err
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()


def test_bad_loop_options_are_refused(tmp_path, capsys):
    rec = _recipe(tmp_path)
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "out", "-j", "0"], capsys)
    assert rc == 2 and "--workers" in err[-1]
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "out", "--scheduler", "nowhere"], capsys)
    assert rc == 2 and len(err) == 1 and "--scheduler" in err[0], err
    assert not (tmp_path / "out").exists()


def test_many_seeds_same_bytes_on_any_worker_count_and_a_killed_run_resumes(tmp_path, capsys, monkeypatch):
    """Two seeds x (ideal, open), 5 steps: the same numbers on 1 and 2 workers, and a run stopped after two
    tasks resumes (computing only the rest) to the same numbers; the scratch folder is removed at the end."""
    import functools
    import json

    from metadesign.execution import Execution
    from metadesign.studies import cli_loop

    rec = _recipe(tmp_path, "steps = 5\nsubsteps = 2\nseeds = 2\n")
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "j1", "-j", "1", "--json"], capsys)
    assert rc == 0, err
    rep = json.loads((tmp_path / "j1" / "loop.json").read_text())
    assert rep["methods"]["ideal"]["seeds"] == 2 and rep["loop"]["seeds"] == 2
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "j2", "-j", "2", "--json"], capsys)
    assert rc == 0, err
    assert _numbers(tmp_path / "j1") == _numbers(tmp_path / "j2")
    assert not (tmp_path / "j1.partial").exists() and not (tmp_path / "j2.partial").exists()

    monkeypatch.setattr(cli_loop, "Execution", functools.partial(Execution, stop_after=2), raising=False)
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "k", "-j", "1", "--json"], capsys)
    assert rc == 130 and "interrupted" in err[-1], err
    kept = sorted(p.name for p in (tmp_path / "k.partial").glob("seed*.npz"))
    assert len(kept) == 2, kept
    monkeypatch.setattr(cli_loop, "Execution", Execution, raising=False)
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "k", "-j", "2"], capsys)
    assert rc == 0, err
    assert any("resuming: 2/4 tasks" in e for e in err), err
    assert _numbers(tmp_path / "k") == _numbers(tmp_path / "j1")
    assert not (tmp_path / "k.partial").exists()


def test_one_seed_is_the_first_realisation_and_seeds_differ():
    from metadesign.studies.loop import flow_seed, noise_stream

    assert flow_seed(7, 0) == 7 and noise_stream(0) == ()
    a, b = flow_seed(7, 1), flow_seed(7, 2)
    assert a.spawn_key != b.spawn_key and a.entropy == b.entropy == 7
    assert noise_stream(1) != noise_stream(2)


def test_pseudo_open_loop_at_one_frame_of_delay_is_the_integrator():
    """At one frame of delay the pseudo-open-loop controller's error ``w_k - c_k`` is the residual's fit (the
    mirror holds the integrator's state): the same series; at two frames it differs, and its theory too."""
    from metadesign.optics.control import Controller, rejection_tf
    from metadesign.studies.loop import IdealPhaseSensor, LoopTiming, pol_rejection_tf, run_loop

    world, steps = _world(8.0, 8), 8
    timing = LoopTiming(2000.0, substeps=2)
    dm = _dm(world)
    plain = run_loop(world, timing, steps, "ideal", IdealPhaseSensor(), dm, Controller(0.5, 1.0, 0.99))
    pol = run_loop(world, timing, steps, "ideal", IdealPhaseSensor(), dm, Controller(0.5, 1.0, 0.99),
                   pseudo_open_loop=True)
    np.testing.assert_allclose(pol["npib"], plain["npib"], rtol=1e-6)
    f = np.linspace(10, 1000, 17)
    np.testing.assert_allclose(pol_rejection_tf(f, 2000.0, 0.5, 1.0, 0.99), rejection_tf(f, 2000.0, 0.5, 1.0, 0.99))
    two = run_loop(world, timing, steps, "ideal", IdealPhaseSensor(), dm, Controller(0.5, 2.0, 0.99),
                   pseudo_open_loop=True)
    assert not np.allclose(two["npib"], plain["npib"])
    assert not np.allclose(pol_rejection_tf(f, 2000.0, 0.5, 2.0), rejection_tf(f, 2000.0, 0.5, 2.0))


def test_the_gain_is_chosen_per_closed_loop_by_the_stated_search(tmp_path, capsys):
    import json

    from metadesign.studies.loop_study import GAIN_GRID

    rec = _recipe(tmp_path, 'steps = 6\nsubsteps = 2\ngain = "optimise"\ngain_steps = 4\n')
    rc, out, err = run_main(["loop", rec, "-o", tmp_path / "out", "--json"], capsys)
    assert rc == 0, err
    rep = json.loads((tmp_path / "out" / "loop.json").read_text())
    s = rep["methods"]["ideal"]["gain_search"]
    assert set(GAIN_GRID) <= set(s["gains"]) and len(s["gains"]) > len(GAIN_GRID)
    best = s["gains"][int(np.argmax(s["npib_mean"]))]
    assert s["gain"] == best == rep["methods"]["ideal"]["gain"] == rep["gain_search"]["chosen"]["ideal"]
    assert "gain" not in rep["methods"]["open"]


def test_the_realtime_method_runs_a_modal_network_in_the_loop(tmp_path, capsys):
    """`[device] realtime` names a modal network; the loop renders its tensor size and runs it through
    ONNX Runtime as the method "realtime", and with its tip and tilt from the push-pull linear reconstructor
    as "realtime_tt", and with them from the in-focus channel's peak as "realtime_peak" (measured latency,
    delay and NPiB reported)."""
    import json

    import torch

    from metadesign.reconstruction.modal_net import ModalNet, ModalNetConfig
    from metadesign.reconstruction.model import save_model

    torch.manual_seed(0)
    save_model(ModalNet(ModalNetConfig(input_size=32, aperture_size=41, modes=10, stride=2, width=4, hidden=8,
                                       bin=4)), tmp_path / "rt.safetensors", {"epoch": 0})
    rec = _recipe(tmp_path, 'steps = 4\nsubsteps = 1\nmethods = ["realtime", "realtime_tt", "realtime_peak", '
                            '"open"]\n')
    rec.write_text(rec.read_text().replace('methods = ["ideal", "open"]\n', "").replace(
        "[loop]", f'realtime = "{tmp_path / "rt.safetensors"}"\n[loop]'))
    rc, _, err = run_main(["loop", rec, "-o", tmp_path / "out", "--json"], capsys)
    assert rc == 0, err
    ms = json.loads((tmp_path / "out" / "loop.json").read_text())["methods"]
    for r in (ms["realtime"], ms["realtime_tt"], ms["realtime_peak"]):  # alone, with the linear or the peak tilt
        assert r["latency_ms"] > 0 and r["delay_frames"] > 1 and 0 <= r["npib_mean"] <= 1.5
