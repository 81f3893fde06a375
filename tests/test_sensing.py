"""Stage 4: as-fabricated forward model against the full angular spectrum and analytic focusing."""

import json

import numpy as np
import pytest
from conftest import run_cli
from scipy.special import fresnel

from metadesign.design import LensChannel, SupercellSpec, select_atoms
from metadesign.design.build import discretize_design
from metadesign.design.recipe import load_design_recipe
from metadesign.design.store import run_design
from metadesign.layouts import write_layout
from metadesign.sensing.forward import asm_reference_intensity, quadrant_fields
from metadesign.sensing.model import AsFabricated, channel_metrics, load_sensing_recipe, render_frames
from metadesign.sensing.sensor import NoiseSpec, add_noise, psf_tensor, quadrant_slices
from metadesign.sensing.transmission import Perturbation, interpolate_t, perturb_widths, pillar_transmission


@pytest.fixture(scope="module")
def demo(tmp_path_factory, repo):
    out = tmp_path_factory.mktemp("demo") / "demo"
    d, _ = run_design(load_design_recipe(repo / "layouts" / "demo.toml"), out)
    write_layout(d, out / "layout.oas")
    return AsFabricated.from_files(out / "layout.oas"), load_sensing_recipe(repo / "sensing" / "demo.toml"), out


@pytest.mark.parametrize("pol", [0, 1])
def test_fast_path_equals_full_angular_spectrum(demo, pol):
    """Coarse pupil (4x4-cell blocks) vs band-limited ASM at pillar pitch, same f-number: <= 1 % L2."""
    fab, sr, _ = demo
    cp = fab.pupil(sr.sensor.distance, sr.pupil_grid)
    t, _ = pillar_transmission(fab.layout.index_map, fab.layout.atom_widths_nm, fab.lib)
    I, coords = asm_reference_intensity(t[..., pol] * fab.tn_scale, fab.period, fab.wavelength,
                                        sr.sensor.distance, 2048)
    for k in range(1, 5):
        cx, cy = sr.sensor.quadrant_centre(k)
        cols = np.nonzero(np.abs(coords - cx) < 22e-6)[0]
        rows = np.nonzero(np.abs(coords - cy) < 17e-6)[0]
        ref = I[np.ix_(rows, cols)]
        fast = quadrant_fields(cp, pol, coords[cols], coords[rows], (cx, cy))
        assert np.linalg.norm(fast - ref) / np.linalg.norm(ref) <= 0.01


def test_discretized_lens_focuses_at_design_focal_length(paper_library):
    """One Eq. 1 lens (f = 10 mm, 1 mm square aperture) discretized on the committed library:
    its on-axis intensity peaks where the analytic Fresnel integral of a perfect square lens does."""
    lib = paper_library
    f, n = 10e-3, 1428
    lens = LensChannel(f, 0.0, 0.0)
    spec = SupercellSpec(1.55e-6, 0.7e-6, n, 1, (lens,), (lens,))
    atoms = select_atoms(lib.t_x, lib.t_y, lib.T0, lib.wx, lib.wy, 0.7, 16, np.sqrt(1 / 1.444))
    res = discretize_design(spec, atoms)
    x = (np.arange(n) - (n - 1) / 2) * 0.7e-6
    zs = f + np.linspace(-0.6e-3, 0.6e-3, 61)
    k0 = 2 * np.pi / 1.55e-6
    a = n * 0.7e-6 / 2
    for pol in (0, 1):
        u = atoms.t[res.index_map, pol]
        I = []
        for z in zs:  # on-axis Fresnel integral, separable chirp
            c = np.exp(1j * k0 * x**2 / (2 * z))
            I.append(abs(c @ u @ c) ** 2 / z**2)
        cz = 1 / zs - 1 / f
        T = a * np.sqrt(2 * np.abs(cz) / 1.55e-6)
        S, C = fresnel(T)
        amp = np.where(np.abs(cz) > 0, 2 * np.sqrt(1.55e-6 / (2 * np.maximum(np.abs(cz), 1e-30))) * np.abs(C + 1j * S), 2 * a)
        I_ref = amp**4 / zs**2
        z_sim, z_ref = zs[np.argmax(I)], zs[np.argmax(I_ref)]
        assert abs(z_sim - z_ref) <= 0.02e-3 + 1e-12  # one sample of the z scan
        assert abs(z_ref - f) < 0.1e-3  # Fresnel number 16: focal shift below 1 %


def test_psf_centres_orientation_and_channel_order(demo):
    fab, sr, _ = demo
    frames, cp = render_frames(fab, sr)
    X, Y = sr.sensor.coords()
    for p in range(2):
        for k in range(1, 5):
            lens = fab.channels[p][k - 1]
            # the channel's own light peaks in its own quadrant near the designed offset
            r, c = quadrant_slices(sr.sensor, k)
            sub = quadrant_fields(cp, p, X[c], Y[r], sr.sensor.quadrant_centre(k), channels=[k - 1], z=lens.focal_length)
            j, i = np.unravel_index(np.argmax(sub), sub.shape)
            assert abs(X[c][i] - lens.offset_x) <= 2 * sr.sensor.focal_pitch
            assert abs(Y[r][j] - lens.offset_y) <= 2 * sr.sensor.focal_pitch
            assert np.sign(X[c][i]) == np.sign(lens.offset_x) and np.sign(Y[r][j]) == np.sign(lens.offset_y)
    # tensor order: [x QI..QIV, y QI..QIV], each the matching quadrant of the frame
    marked = np.zeros_like(frames)
    for p in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sr.sensor, k)
            marked[p, r, c] = 10 * p + k
    t = psf_tensor(marked, sr.sensor)
    assert t.shape == (8, 256, 256)
    # area-weighted: a 320 x 256 quadrant of uniform power v per pixel becomes 256 x 256 pixels of v * 320/256
    qh, qw = sr.sensor.height_px // 2, sr.sensor.width_px // 2
    np.testing.assert_allclose(t.mean(axis=(1, 2)), np.array([1, 2, 3, 4, 11, 12, 13, 14]) * qh * qw / 256**2,
                               rtol=1e-6)


def test_area_resampling_conserves_power_and_matches_box_integral():
    """Independent reference: upsample by an integer factor (pixel replication / area) then box-sum."""
    from metadesign.sensing.sensor import area_resample

    rng = np.random.default_rng(3)
    img = rng.random((40, 50))
    out = area_resample(img, 20)
    assert out.sum() == pytest.approx(img.sum(), rel=1e-6)
    fine = np.kron(img, np.ones((20, 20))) / 400.0  # 800 x 1000 sub-pixels carrying the power
    ref = fine.reshape(20, 40, 20, 50).sum(axis=(1, 3))
    np.testing.assert_allclose(out, ref, rtol=1e-5)
    # a point of power moves with the output pixel it falls on, never split for an aligned factor
    pt = np.zeros((40, 40))
    pt[13, 27] = 1.0
    o = area_resample(pt, 20)
    assert o[6, 13] == pytest.approx(1.0) and o.sum() == pytest.approx(1.0)


def test_energy_budget_of_interleaved_supercell(demo):
    """Only the supercell-averaged field propagates: about 1/4 of T0 reaches the sensor plane."""
    fab, sr, _ = demo
    frames, cp = render_frames(fab, sr)
    aperture = (fab.n_cells * fab.period) ** 2
    for p in range(2):
        prop = float(np.sum(np.abs(cp.G[p].sum(axis=0)) ** 2) * cp.pitch**2) / aperture
        assert 0.2 < prop < 0.3
        assert frames[p].sum() / aperture <= prop * 1.001  # the sensor sees at most the propagating power


def _predicted_strehl_ratio(fab, d, pert, pol, k):
    """Strehl of the perturbed channel over the nominal one from the pillar transmissions alone (no
    propagation): the focus correlates the field with the ideal lens, so the peak is
    |sum t e^{-i phi_lens}|^2 and, at fixed propagating power, Strehl ~ |sum t e^{-i phi}|^2 / sum |t|^2."""
    from metadesign.design.phase import design_phase

    n = fab.n_cells
    iy = np.arange((k - 1) // 2, n, 2)
    ix = np.arange((k - 1) % 2, n, 2)
    phi = design_phase(d.spec, pol, iy, ix, d.offsets[pol], wrapped=False)
    w = fab.layout.atom_widths_nm[fab.layout.index_map[np.ix_(iy, ix)]] * 1e-9
    out = []
    for pp in (Perturbation(), pert):
        wx, wy = perturb_widths(w[..., 0], w[..., 1], pp)
        t = interpolate_t(fab.lib, wx, wy)[0][..., pol]
        out.append(abs(np.sum(t * np.exp(-1j * phi))) ** 2 / np.sum(abs(t) ** 2))
    return out[1] / out[0]


def test_channel_metrics_and_perturbation_response(demo):
    from metadesign.design.store import load_design

    fab, sr, out = demo
    d = load_design(out)
    m0 = channel_metrics(fab.pupil(sr.sensor.distance, sr.pupil_grid), sr.sensor, fab)
    assert len(m0) == 8
    for r in m0:
        assert 0.04 < r["focusing_efficiency"] < 0.07  # ~ T0 / 16, minus crosstalk
        assert 0.95 < r["strehl"] <= 1.0  # a Strehl ratio cannot exceed 1
        assert abs(r["focal_shift_mm"]) < 0.1
        assert r["crosstalk"] < 0.1
    for pert in (Perturbation(-10e-9, -10e-9), Perturbation(15e-9, 15e-9)):
        m1 = channel_metrics(fab.pupil(sr.sensor.distance, sr.pupil_grid, pert), sr.sensor, fab)
        for a, b in zip(m0, m1):
            pol = "xy".index(a["pol"])
            pred = _predicted_strehl_ratio(fab, d, pert, pol, a["k"])
            assert pred < 0.99  # the bias does hurt
            # the prediction counts all scattered power in the normalisation; the propagating-power
            # normalisation of the Strehl leaves out what scatters past the coarse-pupil band (measured:
            # 0.7-0.8 of the predicted drop), so the measured drop lies between 1/2 and all of the prediction
            drop, pred_drop = 1 - b["strehl"] / a["strehl"], 1 - pred
            assert 0.5 * pred_drop < drop <= 1.05 * pred_drop, (a["pol"], a["k"], drop, pred_drop)


def test_interpolation_perturbations_and_clamping(paper_library):
    lib = paper_library
    t, T0, out = interpolate_t(lib, lib.wx[[3, 40]], lib.wy[[7, 70]])
    np.testing.assert_allclose(t[:, 0], lib.t_x[[3, 40], [7, 70]], rtol=1e-6)
    np.testing.assert_allclose(t[:, 1], lib.t_y[[3, 40], [7, 70]], rtol=1e-6)
    assert out == 0
    _, _, out = interpolate_t(lib, np.array([0.52e-6, 0.3e-6]), np.array([0.3e-6, 0.05e-6]))
    assert out == 2
    wx, wy = perturb_widths(np.array([300e-9]), np.array([200e-9]), Perturbation(corner_radius=40e-9))
    assert wx[0] * wy[0] == pytest.approx(300e-9 * 200e-9 - (4 - np.pi) * 40e-9**2, rel=1e-12)
    assert wx[0] / wy[0] == pytest.approx(1.5)
    a = perturb_widths(np.full(1000, 3e-7), np.full(1000, 3e-7), Perturbation(jitter=5e-9, seed=3))
    b = perturb_widths(np.full(1000, 3e-7), np.full(1000, 3e-7), Perturbation(jitter=5e-9, seed=3))
    np.testing.assert_array_equal(a[0], b[0])
    assert np.std(a[0]) == pytest.approx(5e-9, rel=0.1)


def test_noise_recipe_percent_is_converted_once(tmp_path):
    from metadesign.sensing.model import sensing_from_dict
    sr = sensing_from_dict({"noise": {"gaussian_percent": 5.0, "seed": 2}})
    assert sr.noise.gaussian_sigma == pytest.approx(0.05)
    f = np.zeros((2, 64, 64), np.float32)
    f[:, 10, 10] = 2.0
    n = add_noise(f, sr.noise)
    assert np.std(n[0][f[0] == 0]) == pytest.approx(0.1, rel=0.05)  # 5 % of the peak (2.0)


def test_noise_models_seeded():
    f = np.zeros((2, 64, 64), np.float32)
    f[:, 32, 32] = 1.0
    n1 = add_noise(f, NoiseSpec(gaussian_sigma=0.05, seed=4))
    n2 = add_noise(f, NoiseSpec(gaussian_sigma=0.05, seed=4))
    np.testing.assert_array_equal(n1, n2)
    assert np.std(n1[0][f[0] == 0]) == pytest.approx(0.05, rel=0.05)
    q = add_noise(f + 0.3, NoiseSpec(bit_depth=2, seed=0))
    assert len(np.unique(np.round(q[0] / q[0].max() * 3, 6))) <= 4
    s = add_noise(f * 0 + 0.5, NoiseSpec(photons_at_peak=1e4, seed=1))
    assert np.std(s) / np.mean(s) == pytest.approx(1 / np.sqrt(1e4), rel=0.1)


@pytest.mark.slow  # a study run end to end: the default suite's 10-minute budget
def test_psf_and_fab_study_cli(demo, repo):
    _, _, out = demo
    layout = out / "layout.oas"
    p = run_cli("psf", layout, "--sensor", repo / "sensing" / "demo.toml", "--json")
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert s["tensor_shape"] == [8, 256, 256] and (out / "psf" / "psf-fig-2c.png").exists()
    p = run_cli("fab-study", layout, "--sensor", repo / "sensing" / "demo.toml", "--bias-nm", "-5", "0",
                "--jitter-nm", "0", "3", "-o", out / "fs")
    assert p.returncode == 0, p.stderr
    lines = (out / "fs" / "fab-study.csv").read_text().strip().splitlines()
    assert len(lines) == 1 + 4 * 8 and (out / "fs" / "fab-study.png").exists()
    bad = run_cli("psf", layout, "--sensor", repo / "sensing" / "demo.toml", "--jitter-nm", "-1", "-o", out / "x")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and not (out / "x").exists()
    p = run_cli("psf", layout, "--sensor", repo / "sensing" / "demo.toml", "--full-resolution", "32", "--json",
                "-o", out / "full")
    assert p.returncode == 0, p.stderr
    assert max(json.loads(p.stdout)["full_resolution_check"]["rel_l2_per_channel"]) < 0.01
    from metadesign.io import write_npz
    write_npz(out / "wf.npz", {"field": np.ones((10, 10), np.complex64)})
    bad = run_cli("psf", layout, "--sensor", repo / "sensing" / "demo.toml", "--wavefront", out / "wf.npz",
                  "-o", out / "y")
    assert bad.returncode == 2 and "coarse pupil grid" in bad.stderr and not (out / "y").exists()
    p = run_cli("psf", layout, "--sensor", repo / "sensing" / "demo.toml", "--beside", out / "psf" / "psf.npz",
                "-o", out / "beside")  # another device's frames under these (here: the same device)
    assert p.returncode == 0, p.stderr
    assert (out / "beside" / "psf-fig-2c.png").stat().st_size > (out / "psf" / "psf-fig-2c.png").stat().st_size
    bad = run_cli("psf", layout, "--sensor", repo / "sensing" / "paper.toml", "--beside", out / "psf" / "psf.npz",
                  "-o", out / "z")  # the paper's camera is not the demo's
    assert bad.returncode == 2 and "same pixels" in bad.stderr and not (out / "z").exists()


def test_paper_scale_channels_focus_at_table_s1(repo, tmp_path):
    """Full 5 mm design from the committed library: each of the 8 channels focuses at its Table S1
    focal length within 0.1 mm and lands on its (+-240, +-192) um offset within one sensor pixel."""
    d, _ = run_design(load_design_recipe(repo / "layouts" / "paper-5mm.toml"), tmp_path / "paper")
    write_layout(d, tmp_path / "paper" / "layout.oas")
    fab = AsFabricated.from_files(tmp_path / "paper" / "layout.oas")
    sr = load_sensing_recipe(repo / "sensing" / "paper.toml")
    cp = fab.pupil(sr.sensor.distance, sr.pupil_grid)
    for r in channel_metrics(cp, sr.sensor, fab, focus_span=0.4e-3, n_focus=9):
        assert abs(r["focal_shift_mm"]) < 0.1, r
        assert max(abs(v) for v in r["centroid_shift_um"]) < 1.5, r  # one sensor pixel (1.5 um in focus plane)
    X, Y = sr.sensor.coords()
    for p in range(2):
        for k in range(1, 5):
            lens = fab.channels[p][k - 1]
            r, c = quadrant_slices(sr.sensor, k)
            sub = quadrant_fields(cp, p, X[c], Y[r], sr.sensor.quadrant_centre(k), channels=[k - 1],
                                  z=lens.focal_length)
            j, i = np.unravel_index(np.argmax(sub), sub.shape)
            assert abs(X[c][i] - lens.offset_x) <= sr.sensor.focal_pitch
            assert abs(Y[r][j] - lens.offset_y) <= sr.sensor.focal_pitch
