"""A device under a costly forward model, sampled (issue #34): the correction pupil against its definition,
the U-statistic against the exact device, unbiasedness where a naive square is biased, and the CLI."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import run_cli, run_main

from metadesign.conventions import centered
from metadesign.design.recipe import load_design_recipe
from metadesign.design.store import load_design, run_design
from metadesign.library.peds import PedsModel, certified_t
from metadesign.library.store import interpolate_t, load_library
from metadesign.reconstruction.dataset import load_device
from metadesign.reconstruction.model import UNetConfig, build_unet, save_model
from metadesign.sensing.forward import CoarsePupil, coarse_pupil, quadrant_fields, sensor_frames
from metadesign.studies.lpa import Downstream, pupil_downstream
from metadesign.sensing.model import AsFabricated, load_sensing_recipe, spot_metrics
from metadesign.sensing.transmission import Perturbation, unit_t_as_made
from metadesign.sensing.sampled import (
    SampledIntensity,
    delta_pupil,
    device_widths_rows,
    eligible_supercells,
    jackknife_se,
    sampled_frames,
    sampled_spot_metrics,
    supercell_widths,
)


@pytest.fixture(scope="module")
def demo(tmp_path_factory, repo):
    out = tmp_path_factory.mktemp("sampled") / "demo"
    d, _ = run_design(load_design_recipe(repo / "layouts" / "demo.toml"), out)
    fab = AsFabricated.from_design(d)
    sr = load_sensing_recipe(repo / "sensing" / "demo.toml")
    return fab, sr, fab.pupil(sr.sensor.distance, sr.pupil_grid), out


def _plus(cp, d):
    return CoarsePupil(cp.G + d.G, cp.X, cp.block, cp.period, cp.wavelength, cp.z, 0)


def _corrections(fab, ids, seed=1):
    """A systematic part (a tenth of each supercell's own t: it changes the focused power) and a random one
    (it scatters), of the size of the certified model's corrections to the coupling model."""
    w = supercell_widths(fab, ids)
    t = interpolate_t(fab.lib, w[..., 0], w[..., 1])[0].mean((1, 2))
    rng = np.random.default_rng(seed)
    return (-0.1 + 0.05j) * t + 0.15 * (rng.normal(size=t.shape) + 1j * rng.normal(size=t.shape))


def test_supercells_and_their_widths(demo):
    fab, _, _, _ = demo
    ids = eligible_supercells(fab)
    C2 = fab.n_cells // 2
    im = fab.layout.index_map
    full = (im[:2 * C2, :2 * C2] >= 0).reshape(C2, 2, C2, 2).all((1, 3))  # the demo's square aperture
    assert np.array_equal(ids, np.flatnonzero(full))
    pick = ids[[0, len(ids) // 3, -1]]
    w = supercell_widths(fab, pick)
    for s, i in enumerate(pick):
        I, J = divmod(int(i), C2)
        for r in range(2):
            for c in range(2):
                k = im[2 * I + r, 2 * J + c]
                assert np.allclose(w[s, r, c], fab.layout.atom_widths_nm[k] * 1e-9)


def test_sampled_supercells_are_the_designs_atoms_targets_and_widths(demo):
    """Atoms and targets read supercell by supercell equal the design's whole rows (``supercell_targets``),
    and the atoms' widths are the device's (``supercell_widths``)."""
    from metadesign.design.compensate import _blocks, sampled_supercells, supercell_targets

    fab, _, _, out = demo
    d = load_design(out)
    n, C2 = d.spec.n_cells - d.spec.n_cells % 2, d.spec.n_cells // 2
    ids = eligible_supercells(fab)
    ids = ids[np.random.default_rng(0).choice(len(ids), 40, replace=False)]
    a, S = sampled_supercells(d, ids)
    flat = (ids // C2) * (n // 2) + ids % C2
    np.testing.assert_array_equal(a, _blocks(d.atom_indices()[:n].astype(np.int64))[flat])
    np.testing.assert_allclose(S, supercell_targets(d, 0, n)[flat], atol=2e-6)
    aw = np.stack([d.atoms.wx, d.atoms.wy], 1)
    np.testing.assert_allclose(aw[a], supercell_widths(fab, ids), rtol=0, atol=1e-15)


def test_a_jittered_device_is_one_device(demo):
    """The replayed widths of a jittered device (bias 3 nm, jitter 5 nm) rebuild, through the library alone,
    the pupil the forward model makes of it: the sample's supercells are the device's own pillars."""
    fab, sr, _, _ = demo
    z, grid = sr.sensor.distance, sr.pupil_grid
    pert = Perturbation.from_nm(3.0, jitter_nm=5.0, seed=11)
    ref = fab.pupil(z, grid, pert)
    st = fab.lib.meta["stack"]
    bare = 2 * st["n_substrate"] / (st["n_substrate"] + st["n_superstrate"])
    tiles = device_widths_rows(fab, grid, pert)

    def rows(r0, r1):
        a, b, w, has = next(tiles)
        assert (a, b) == (r0, r1)
        t = interpolate_t(fab.lib, w[..., 0], w[..., 1])[0]
        t[~has] = bare
        return t, 0

    got = coarse_pupil(rows, fab.n_cells, fab.period, fab.wavelength, z, fab.pupil_block(grid), 2, fab.tn_scale)
    assert np.abs(got.G - ref.G).max() < 1e-5 * np.abs(ref.G).max()
    assert np.abs(fab.pupil(z, grid).G - ref.G).max() > 1e-3 * np.abs(ref.G).max()  # the jitter is there
    ids = eligible_supercells(fab)[::997]
    dw = supercell_widths(fab, ids, pert, grid) - supercell_widths(fab, ids) - 3e-9
    assert abs(dw.mean()) < 1e-9 and 4e-9 < dw.std() < 6e-9


def test_delta_pupil_is_the_block_sum_of_its_definition(demo):
    """Against the coarse pupil's definition written out per pillar: G[p, a + 2b, block] += tn * delta *
    chirp(y) chirp(x) / B^2 for the four pillars (2I + b, 2J + a) of each corrected supercell."""
    fab, sr, _, _ = demo
    z, grid = sr.sensor.distance, sr.pupil_grid
    ids = eligible_supercells(fab)
    pick = ids[[5, 5, 900, len(ids) // 2, -3]]  # a supercell drawn twice counts twice
    delta = _corrections(fab, pick, 7)
    got = delta_pupil(fab, z, grid, pick, delta, 3.0).G
    B = fab.pupil_block(grid)
    k0 = 2 * np.pi / fab.wavelength
    x = centered(fab.n_cells, fab.period)[0] + np.arange(fab.n_cells) * fab.period
    chirp = np.exp(1j * k0 * x**2 / (2 * z))
    ref = np.zeros(got.shape, complex)
    C2 = fab.n_cells // 2
    for s, i in enumerate(pick):
        I, J = divmod(int(i), C2)
        for b in range(2):
            for a in range(2):
                row, col = 2 * I + b, 2 * J + a
                ref[:, a + 2 * b, row // B, col // B] += (fab.tn_scale * 3.0 * delta[s] * chirp[row] * chirp[col]
                                                          / B**2)
    assert np.abs(got - ref).max() < 1e-5 * np.abs(ref).max()
    assert np.count_nonzero(np.abs(ref).sum((0, 1))) == 4  # four blocks touched (one twice)


def test_exact_replicates_give_the_device(demo):
    """Replicates that all carry the whole correction (every supercell, weight 1) are the corrected
    device: the U-statistic is then its intensity exactly, and the jackknife's error bars vanish."""
    fab, sr, cp, _ = demo
    z, grid = sr.sensor.distance, sr.pupil_grid
    ids = eligible_supercells(fab)
    d = delta_pupil(fab, z, grid, ids, _corrections(fab, ids), 1.0)
    exact = spot_metrics(_plus(cp, d), sr.sensor, fab)
    rows, loo = sampled_spot_metrics(cp, [d, d, d], sr.sensor, fab)
    base = spot_metrics(cp, sr.sensor, fab)
    assert abs(exact[0]["spot_efficiency"] / base[0]["spot_efficiency"] - 1) > 0.05  # the correction matters
    for e, r, *lo in zip(exact, rows, *loo):
        for k in ("spot_efficiency", "spot_strehl", "focal_shift_mm"):
            # the device's intensities are float32, the estimate's float64: the parabolic refinement of the
            # best focus turns that rounding into nanometres
            assert r[k] == pytest.approx(e[k], rel=1e-5, abs=1e-5 if k == "focal_shift_mm" else 1e-9)
            assert jackknife_se([x[k] for x in lo]) < 1e-6 * max(abs(e[k]), 1e-3)


def test_sampled_intensity_is_unbiased_where_a_square_is_not(demo):
    """Between two spots, where the sampled correction's noise dominates: over many independent samples the
    U-statistic averages to the corrected device's intensity, the square of the averaged field does not
    (its excess is the sample's noise power); the jackknife's error bar matches the spread of estimates."""
    fab, sr, cp, _ = demo
    z, grid = sr.sensor.distance, sr.pupil_grid
    ids = eligible_supercells(fab)
    delta = _corrections(fab, ids)
    exact_cp = _plus(cp, delta_pupil(fab, z, grid, ids, delta, 1.0))
    c1, c2 = sr.sensor.quadrant_centre(1), sr.sensor.quadrant_centre(2)
    xo = np.linspace(-20e-6, 20e-6, 9) + 0.5 * (c1[0] + c2[0])  # the gap between quadrants I and II
    yo = np.linspace(-20e-6, 20e-6, 9) + c1[1]
    exact = quadrant_fields(exact_cp, 0, xo, yo, c1).mean()
    R, m, runs = 4, 20, 120
    u, naive, se = [], [], []
    for seed in range(runs):
        pick = np.random.default_rng(seed).integers(0, len(ids), R * m)
        reps = [delta_pupil(fab, z, grid, ids[pick[r * m:(r + 1) * m]], delta[pick[r * m:(r + 1) * m]],
                            len(ids) / m) for r in range(R)]
        si = SampledIntensity(cp, reps)
        u.append(si(0, xo, yo, c1).mean())
        lo = []
        for r in range(R):
            si.active = tuple(i for i in range(R) if i != r)
            lo.append(si(0, xo, yo, c1).mean())
        se.append(jackknife_se(lo))
        mean_cp = _plus(cp, CoarsePupil(sum(d.G for d in reps) / R, cp.X, cp.block, cp.period, cp.wavelength,
                                        cp.z, 0))
        naive.append(quadrant_fields(mean_cp, 0, xo, yo, c1).mean())
    u, naive = np.array(u), np.array(naive)
    sem = u.std() / np.sqrt(runs)
    assert abs(u.mean() - exact) < 4 * sem, (u.mean(), exact, sem)
    assert naive.mean() - exact > 5 * naive.std() / np.sqrt(runs)  # the square is biased up by the noise
    assert 0.6 < np.mean(se) / u.std() < 1.4


def test_coupling_check_certified_cli(demo, tmp_path, repo, capsys):
    fab, _, _, out = demo
    res = run_cli("library", "coupling-check", str(out), "--sensor", repo / "sensing" / "demo.toml", "--certified", "6",
                  "--replicates", "3", "--jitter-nm", "5", "--ring", "3", "-j", "1", "-o", str(tmp_path / "cc"), "--json")
    assert res.returncode == 0, res.stderr
    rep = json.loads(res.stdout)
    c = rep["cases"]["certified"]
    assert rep["cases"]["certified_ring"]["ring"]["supercells"] == 3  # the ring on the same jittered sample
    assert c["sampling"]["supercells"] == 6 and c["sampling"]["eligible_supercells"] == (fab.n_cells // 2) ** 2
    assert rep["jitter_nm"] == pytest.approx(5.0)
    assert set(c["stderr"]) == {"spot_efficiency", "spot_strehl", "stray", "focal_shift_mm"}
    assert all(np.isfinite(v) and v >= 0 for v in c["stderr"].values())
    assert (tmp_path / "cc" / "coupling-metrics.png").exists() and not (tmp_path / "cc.partial").exists()
    res = run_cli("library", "coupling-check", str(out), "--sensor", repo / "sensing" / "demo.toml", "--bias-nm", "4",
                  "--jitter-nm", "5", "-o", str(tmp_path / "cc4"))
    assert res.returncode == 0, res.stderr
    res = run_cli("library", "coupling-sweep", str(tmp_path / "cc4"), str(tmp_path / "cc"), "-o",
                  str(tmp_path / "sweep.png"), "--json")
    assert res.returncode == 0, res.stderr
    sweep = json.loads(res.stdout)
    assert sweep["bias_nm"] == [0.0, 4.0] and (tmp_path / "sweep.png").exists()
    assert set(sweep["cases"]) == {"lpa", "coupled"}  # the certified case is not in both reports
    other = json.loads((tmp_path / "cc4" / "coupling-check.json").read_text())
    assert other["design"]["sha256"] == rep["design"]["sha256"]
    other["design"]["sha256"] = "0" * 64  # a report of another design
    other["bias_nm"] = [8.0, 8.0]
    (tmp_path / "other.json").write_text(json.dumps(other))
    # the refusals in-process (one line, exit 2, nothing written; no interpreter start-up per case)
    rc, _, err = run_main(["library", "coupling-sweep", tmp_path / "cc", tmp_path / "other.json", "-o",
                           tmp_path / "mixed.png"], capsys)
    assert rc == 2 and "different designs" in " ".join(err) and not (tmp_path / "mixed.png").exists()
    rc, _, err = run_main(["library", "coupling-sweep", tmp_path / "cc", tmp_path / "cc", "-o",
                           tmp_path / "same.png"], capsys)
    assert rc == 2 and "repeat" in " ".join(err) and not (tmp_path / "same.png").exists()
    rc, _, err = run_main(["library", "coupling-check", out, "--certified", "5", "--replicates", "3",
                           "-o", tmp_path / "bad"], capsys)
    assert rc == 2 and len(err) == 1 and "--certified" in err[0]
    rc, _, err = run_main(["library", "coupling-check", out, "--ring", "8", "-o", tmp_path / "bad"], capsys)
    assert rc == 2 and len(err) == 1 and "--ring" in err[0]
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow  # a study run end to end: the default suite's 10-minute budget
def test_etch_depth_under_every_model_and_its_sweep(demo, repo, tmp_path, capsys):
    """An etch-depth error (and a sloped wall) through coupling-check (in-process; the subprocess path is
    the test above): the coupled and certified devices take
    the fab library's unit cells at that height and angle (the LPA case is the fab-study's device), the
    certified solves at that height, tapered (its four-identical-pillars limit is the as-made unit cell,
    whatever the height); the sweep finds its axis; bad values are one line and write nothing."""
    fab, sr, _, out = demo
    F = load_library(repo / "library" / "paper-fab.npz")
    pert = Perturbation.from_nm(height_nm=25.0)
    w = np.full((2, 2, 2, 2), 0.2e-6)
    w[1] = 0.31e-6
    tu = unit_t_as_made(fab.lib, w[..., 0], w[..., 1], pert, F)
    assert np.abs(tu - interpolate_t(fab.lib, w[..., 0], w[..., 1])[0]).min() > 1e-3  # the height matters
    etched = replace(fab.lib.stack, height=fab.lib.stack.height + 25e-9)
    t = certified_t(fab.lib, w, tmp_path / "p", PedsModel((25, 41), (0.4 - 0.2j, 0.9 + 0.1j), fab.lib.identity),
                    stack=etched, t_unit=tu)
    np.testing.assert_allclose(t, tu[:, 0, 0], atol=1e-7)  # identical pillars: no coupling at any height

    base = ("library", "coupling-check", str(out), "--sensor", repo / "sensing" / "demo.toml", "-j", "1")
    runs = {}
    for h, cert in (("0", ()), ("25", ("--certified", "6", "--replicates", "3"))):
        rc, out_json, err = run_main([*base, *cert, "--height-nm", h, "--sidewall-deg", "88", "--fab-library",
                                      repo / "library" / "paper-fab.npz", "-o", tmp_path / f"h{h}", "--json"], capsys)
        assert rc == 0, err
        runs[h] = json.loads(out_json)
    assert runs["25"]["height_nm"] == pytest.approx(25.0) and runs["25"]["sidewall_deg"] == 88.0
    assert runs["25"]["cases"]["certified"]["peds"]["taper"] == [88.0, 4]  # its low fidelity tapered
    lpa0, lpa25 = (runs[h]["cases"]["lpa"]["mean"]["spot_efficiency"] for h in ("0", "25"))
    assert lpa25 != pytest.approx(lpa0, rel=1e-4)
    rc, out_json, err = run_main(["library", "coupling-sweep", tmp_path / "h25", tmp_path / "h0", "-o",
                                  tmp_path / "etch.png", "--json"], capsys)
    assert rc == 0, err
    table = json.loads(out_json)
    assert table["axis"] == "height_nm" and table["height_nm"] == [0.0, 25.0]
    assert set(table["cases"]) == {"lpa", "coupled"}  # the certified case only in one
    for args, msg in ((("--height-nm", "25"), "--fab-library"),
                      (("--height-nm", "60", "--fab-library", repo / "library" / "paper-fab.npz"), "spans"),
                      (("--sidewall-deg", "85", "--fab-library", repo / "library" / "paper-fab.npz"), "spans")):
        rc, _, err = run_main([*base, *args, "-o", tmp_path / "bad"], capsys)  # in-process
        assert rc == 2 and len(err) == 1 and msg in err[0], err
        assert not (tmp_path / "bad").exists() and not (tmp_path / "bad.partial").exists()


def test_sampled_frames_and_npib_of_exact_replicates(demo_products, tiny_dataset, tmp_path):
    """Replicates that all carry the whole correction give the corrected device itself: its sensor frames
    (against :func:`sensor_frames` of the summed pupil) and a U-Net's NPiB on re-rendered test samples
    (against the same through the summed pupil), with a zero jackknife error bar; a real correction
    changes the NPiB (the check can fail)."""
    fab = AsFabricated.from_design(load_design(demo_products["design"]))
    dev = load_device(tiny_dataset)
    cp, grid = dev.pupil, dev.pupil.G.shape[-1]
    ids = eligible_supercells(fab)[::7]
    D = delta_pupil(fab, cp.z, grid, ids, 3 * _corrections(fab, ids), 7.0)
    assert D.G.shape == cp.G.shape and np.allclose(D.X, cp.X)
    exact = _plus(cp, D)
    e = np.ones((grid, grid), np.complex64) * np.exp(0.3j)
    frames, loo = sampled_frames(cp, [D, D, D], dev.sensor, e)
    ref = sensor_frames(exact, dev.sensor, e)
    np.testing.assert_allclose(frames, ref, rtol=1e-4, atol=1e-6 * ref.max())
    np.testing.assert_allclose(loo, np.broadcast_to(ref, loo.shape), rtol=1e-4, atol=1e-6 * ref.max())
    torch.manual_seed(0)
    net = build_unet(UNetConfig(base=4, depth=3, input_size=16))
    with torch.no_grad():  # an untrained U-Net's zeroed output layer would ignore its input
        for prm in net.parameters():
            if not prm.abs().sum():
                prm.normal_(0.0, 0.3)
    model = tmp_path / "m.safetensors"
    save_model(net, model, {"noise_percent": 0})
    out = pupil_downstream({"base": cp, "exact": exact}, Downstream(tiny_dataset, model, samples=4), fab,
                           sampled={"sampled": ("base", [D, D, D])})
    s = out["sampled"]
    assert s["npib_unet"] == pytest.approx(out["exact"]["npib_unet"], abs=1e-5)
    assert s["npib_unet_se"] < 1e-5 and s["replicates"] == 3
    assert abs(out["exact"]["npib_unet"] - out["base"]["npib_unet"]) > 1e-5


def test_certified_case_with_the_neighbour_ring(demo, tmp_path):
    """The ring by overlapping windows on a sub-sample of the certified sample: none asked, the case is the
    plain one; asked, every supercell whose +x, +y and +x+y neighbours exist (the demo's square aperture:
    all but the last row and column) gets its ring term from three straddling windows, and the device
    moves."""
    from metadesign.studies.coupling_check import CertifiedSettings, SampledDevice, certified_case

    fab, sr, cp, _ = demo
    fc = fab.with_coupling("supercell")
    cpc = fc.pupil(sr.sensor.distance, sr.pupil_grid)
    peds = PedsModel((25,), (0.8 + 0.1j,), fab.lib.identity)
    st = CertifiedSettings(supercells=12, replicates=3, peds=peds, seed=4)
    dev = SampledDevice(fc, cpc, sr.sensor, sr.pupil_grid)
    base = certified_case(dev, st, tmp_path / "a")
    both = certified_case(dev, replace(st, ring_supercells=6), tmp_path / "c")
    ring = both.pop("with_ring")
    assert base["ring"] is None and "with_ring" not in base and ring["ring"]["supercells"] == 6
    assert "windows" in ring["label"] and "windows" not in both["label"]
    for k in ("spot_efficiency", "spot_strehl", "stray", "focal_shift_mm"):  # the plain case: the same sample
        assert both["mean"][k] == base["mean"][k] and both["stderr"][k] == base["stderr"][k]
    C2 = fab.n_cells // 2
    pick = eligible_supercells(fab)[np.random.default_rng(4).integers(0, C2 * C2, 12)]
    first = pick.reshape(3, 4)[:, :2].ravel()
    inner = int(((first % C2 < C2 - 1) & (first // C2 < C2 - 1)).sum())
    assert ring["ring"]["with_neighbours"] == inner > 0 and ring["ring"]["windows"] == 3 * inner
    for k in ("spot_efficiency", "spot_strehl"):
        assert abs(ring["mean"][k] - base["mean"][k]) > 1e-6 * abs(base["mean"][k])
        eff = ring["ring"]["effect"][k]
        assert eff["mean"] == pytest.approx(ring["mean"][k] - base["mean"][k]) and eff["stderr"] > 0


def test_certified_case_with_its_atoms_reoptimised(demo, tmp_path):
    """The sampled supercells' atoms re-chosen under the certified model: the plain case is the same
    sample's; every supercell's cost towards its target falls or stays; (K - 1) solves per supercell and
    position; the effect is the difference of the two cases; a design that is not the device's, or a
    perturbed device, is refused."""
    from metadesign.studies.coupling_check import CertifiedSettings, SampledDevice, certified_case

    fab, sr, cp, out = demo
    d = load_design(out)
    fc = fab.with_coupling("supercell")
    cpc = fc.pupil(sr.sensor.distance, sr.pupil_grid)
    peds = PedsModel((25,), (0.8 + 0.1j,), fab.lib.identity)
    st = CertifiedSettings(supercells=12, replicates=3, peds=peds, seed=4)
    dev = SampledDevice(fc, cpc, sr.sensor, sr.pupil_grid, design=d)
    base = certified_case(dev, st, tmp_path / "a")
    both = certified_case(dev, replace(st, reoptimise=3), tmp_path / "b")
    reo = both.pop("reoptimised")
    for k in ("spot_efficiency", "spot_strehl", "stray", "focal_shift_mm"):
        assert both["mean"][k] == base["mean"][k] and both["stderr"][k] == base["stderr"][k]
        eff = reo["reoptimise"]["effect"][k]
        assert eff["mean"] == pytest.approx(reo["mean"][k] - base["mean"][k]) and eff["stderr"] >= 0
    assert reo["label"].endswith("atoms re-chosen under it")
    r = reo["reoptimise"]
    assert r["solves"] == 12 * 4 * 2 and r["neighbours"] == 3 and 0 < r["pillars_changed_fraction"] <= 1
    assert sum(v * v for v in r["residual_rms_after"]) < sum(v * v for v in r["residual_rms_before"])
    assert abs(reo["mean"]["spot_strehl"] - base["mean"]["spot_strehl"]) > 0
    other = replace(d, index_map=np.roll(d.index_map, 1, axis=1))
    with pytest.raises(ValueError, match="not the device's"):
        certified_case(replace(dev, design=other), replace(st, reoptimise=3), tmp_path / "c")
    with pytest.raises(ValueError, match="nominal device"):
        certified_case(replace(dev, pert=Perturbation.from_nm(5.0)), replace(st, reoptimise=3), tmp_path / "d")


def test_pillars_of_sampled_supercells_are_the_coupled_devices(demo):
    """Each pillar's ``t`` under the coupling model, for supercells taken out of the device (what the
    re-optimised case moves pillar by pillar), equals the coupled device's own pillar map there, and its
    mean over the supercell is the model's supercell ``t``; a per-pillar correction equal on the four
    pillars is the per-supercell one."""
    from metadesign.library.coupling_net import coupling_t
    from metadesign.sensing.transmission import pillar_transmission
    from metadesign.studies.coupling_check import _pillar_t

    fab, sr, _, _ = demo
    fc = fab.with_coupling("supercell")
    ids = eligible_supercells(fab)[np.random.default_rng(2).choice(len(eligible_supercells(fab)), 30, replace=False)]
    w = supercell_widths(fc, ids)
    got = _pillar_t(fc, w)
    C2 = fab.n_cells // 2
    I, J = ids // C2, ids % C2
    rows = np.unique(np.concatenate([2 * I, 2 * I + 1]))
    r0, r1 = int(rows.min()) // 2 * 2, int(rows.max()) + 1
    t_map, _ = pillar_transmission(fc.layout.index_map, fc.layout.atom_widths_nm, fc.lib, Perturbation(),
                                   slice(r0, r1), None, fc.fab_lib, fc.coupling)
    want = np.stack([t_map[2 * I + r - r0, 2 * J + c] for r in (0, 1) for c in (0, 1)], 1).reshape(-1, 2, 2, 2)
    np.testing.assert_allclose(got, want, atol=2e-5)
    tu = unit_t_as_made(fc.lib, w[..., 0], w[..., 1], Perturbation(), fc.fab_lib)
    np.testing.assert_allclose(got.mean((1, 2)), coupling_t(fc.coupling, w, tu), atol=2e-5)
    assert np.abs(got - tu).max() > 1e-2  # the coupling terms are there
    delta = np.random.default_rng(3).normal(size=(30, 2)) + 0j
    a = delta_pupil(fc, sr.sensor.distance, sr.pupil_grid, ids, delta, 2.0)
    b = delta_pupil(fc, sr.sensor.distance, sr.pupil_grid, ids, np.repeat(np.repeat(delta[:, None, None], 2, 1), 2, 2),
                    2.0)
    np.testing.assert_array_equal(a.G, b.G)


@pytest.mark.parametrize("extra, says", [(["--reoptimise", "3"], "give --certified"),
                                         (["--certified", "6", "--replicates", "3", "--reoptimise", "1"], "at least 2"),
                                         (["--certified", "6", "--replicates", "3", "--reoptimise", "3",
                                           "--jitter-nm", "5"], "nominal device")])
def test_reoptimise_needs_a_certified_nominal_sample(demo, tmp_path, repo, capsys, extra, says):
    _, _, _, out = demo
    rc, _, err = run_main(["library", "coupling-check", out, "--sensor", repo / "sensing" / "demo.toml",
                           "-o", tmp_path / "cc", *extra], capsys)
    assert rc == 2 and len(err) == 1 and says in err[0] and not (tmp_path / "cc").exists()
