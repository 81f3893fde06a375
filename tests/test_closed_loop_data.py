"""Training beacons as a closed loop's sensor sees them (``[closed_loop]`` of a dataset recipe, #50): the open-loop
samples are the plain dataset's bit for bit, a residual is the same beacon with a phase-only correction that
lowers its phase error, rendered through the loop's path, and its NPiB counts the mirror it was seen through."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import tiny_dataset_recipe

from metadesign.reconstruction.dataset import build_dataset, load_dataset_recipe

LOOP = "[closed_loop]\nfraction = 0.6\ngain = [0.6, 1.0]\nactuators = 6\n"


@pytest.fixture(scope="module")
def loop_dataset(tmp_path_factory, demo_products):
    base = tmp_path_factory.mktemp("loop-ds")
    rec = load_dataset_recipe(tiny_dataset_recipe(base, demo_products["layout"], extra=LOOP))
    build_dataset(rec, base / "ds", workers=1)
    return base / "ds"


def _group(path):
    import zarr

    return zarr.open_group(str(path), mode="r")


def _unwrapped_rms(u, mask):
    """rms of the least-squares unwrapped phase on ``mask`` (an independent numpy route: scipy's DCT Poisson
    solve is the project's; here the plain residual of a gradient fit by lstsq)."""
    ph = np.angle(u)
    m = mask
    idx = -np.ones(m.shape, int)
    idx[m] = np.arange(m.sum())
    rows, rhs = [], []
    for dy, dx in ((0, 1), (1, 0)):
        a = m[: m.shape[0] - dy, : m.shape[1] - dx] & m[dy:, dx:]
        i0, i1 = idx[: m.shape[0] - dy, : m.shape[1] - dx][a], idx[dy:, dx:][a]
        d = np.angle(np.exp(1j * (ph[dy:, dx:][a] - ph[: m.shape[0] - dy, : m.shape[1] - dx][a])))
        for p, q, v in zip(i0, i1, d):
            rows.append((p, q))
            rhs.append(v)
    A = np.zeros((len(rows) + 1, m.sum()))
    for k, (p, q) in enumerate(rows):
        A[k, p], A[k, q] = -1.0, 1.0
    A[-1] = 1.0  # piston 0
    sol = np.linalg.lstsq(A, np.r_[rhs, 0.0], rcond=None)[0]
    return float(np.std(sol))


def test_residual_beacons_are_the_open_loop_ones_corrected(loop_dataset, tiny_dataset, demo_products):
    from metadesign.reconstruction.dataset import open_dataset
    from metadesign.sensing.device import Device, ReceiverCrop
    from metadesign.turbulence.chain import BeaconChain

    g, o = _group(loop_dataset), _group(tiny_dataset)
    gain, split = np.asarray(g["loop_gain"][:]), np.asarray(g["split"][:])
    assert np.all(gain[split == 2] == 0)  # the test split stays open loop
    res = np.flatnonzero(gain > 0)
    assert len(res) >= 3 and np.all((gain[res] >= 0.6) & (gain[res] <= 1.0))
    same = np.flatnonzero(gain == 0)
    for k in ("psf", "received", "seed", "rytov"):  # the open-loop samples: the plain dataset's, bit for bit
        np.testing.assert_array_equal(np.asarray(g[k][:])[same], np.asarray(o[k][:])[same], err_msg=k)
    info = open_dataset(loop_dataset)
    a = info.attrs["received_crop"]
    rec_o, rec_c = np.asarray(o["received"][:])[res], np.asarray(g["received"][:])[res]
    mask = np.abs(rec_o[0]) > 0
    for u0, u1 in zip(rec_o, rec_c):
        np.testing.assert_allclose(np.abs(u1), np.abs(u0), rtol=1e-5, atol=1e-6)  # a phase-only mirror
        assert _unwrapped_rms(u1, mask) < 0.7 * _unwrapped_rms(u0, mask)  # gain >= 0.6 of a converged fit
    m = np.asarray(g["mirror_phase"][:])
    assert np.all(m[same] == 0)
    for u0, u1, mk in zip(rec_o, rec_c, m[res]):  # the stored mirror phase is what was taken off
        np.testing.assert_allclose(u1 * np.exp(1j * mk), u0, atol=2e-5)
    # the residual's PSFs are the loop's render of the stored field (Device fed from the crop)
    from metadesign.turbulence.scenario import load_scenario
    from metadesign.turbulence.system import build_system

    rec = load_dataset_recipe(loop_dataset.parent / "tiny.toml")
    sc = load_scenario(rec.turbulence)
    system = build_system(rec.layout, rec.sensor, sc, rec.fabrication, rec.source.parent, rec.tensor_size)
    chain = BeaconChain.for_device(system.device, system.sensing, sc, system.perturbation)
    dev = Device(chain.pupil, chain.sensing.sensor, ReceiverCrop.of_scenario(sc, a["start"], a["size"]))
    t = dev.render(dev.pupil_field(rec_c[0])).psfs
    np.testing.assert_allclose(np.asarray(g["psf"][int(res[0])]), t * (8.0 / t.sum()), rtol=1e-4, atol=1e-6)


def test_npib_of_a_residual_counts_its_mirror(loop_dataset, tiny_dataset):
    """Through the dataset's screens, a residual corrected by its own unwrapped-free phase conjugate reaches
    the open-loop beacon's phase-conjugate NPiB (the same total correction), and with no estimate it scores
    the mirror alone, which beats the open beacon's flat NPiB (the mirror corrects at gain >= 0.6)."""
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.losses import PiB
    from metadesign.reconstruction.metrics import npib_rows

    dl, do = PSFDataset(loop_dataset, "train", screens=True), PSFDataset(tiny_dataset, "train", screens=True)
    assert dl.loop_residuals >= 3 and do.loop_residuals == 0
    k = next(j for j in range(len(dl)) if dl.get(j)["loop_gain"] > 0)
    sl, so = dl[k], do[k]
    c0, a = dl.crop()
    pib = PiB(dl.scenario(), c0, a)
    scr, zero = sl["screens"][None], torch.zeros(1, a, a)
    rl = npib_rows(pib, torch.angle(sl["received"])[None] * pib.ap, scr, sl["received"][None], mirror=sl["mirror"][None])
    ro = npib_rows(pib, zero, so["screens"][None], so["received"][None])
    assert float(rl["phase_conjugate"][0]) == pytest.approx(float(ro["phase_conjugate"][0]), rel=1e-4)
    assert float(rl["estimate"][0]) == pytest.approx(float(ro["phase_conjugate"][0]), rel=0.02)
    assert float(rl["none"][0]) > float(ro["none"][0])


def test_evaluate_refuses_a_split_of_residuals(loop_dataset, tmp_path, capsys):
    from conftest import run_main, tiny_model

    m = tiny_model(tmp_path)
    rc, _, err = run_main(["evaluate", m, loop_dataset, "--split", "train", "-o", tmp_path / "ev"], capsys)
    assert rc == 2 and len(err) == 1 and "closed-loop" in err[0], err
    assert not (tmp_path / "ev").exists()


@pytest.mark.parametrize("bad, match", [("fraction = 1.5", "closed_loop.fraction"),
                                        ("fraction = nan", "closed_loop.fraction"),
                                        ("fraction = 0.5\ngain = [0.9, 0.2]", "closed_loop.gain"),
                                        ("fraction = 0.5\nactuators = 1", "closed_loop.actuators"),
                                        ("fraction = 0.5\ncoupling = 1.0", "closed_loop.coupling")])
def test_bad_closed_loop_sections_exit_2_with_one_line(bad, match, demo_products, tmp_path, capsys):
    from conftest import run_main

    p = tiny_dataset_recipe(tmp_path, demo_products["layout"], extra=f"[closed_loop]\n{bad}\n")
    rc, _, err = run_main(["dataset", "build", p, "-o", tmp_path / "ds"], capsys)
    assert rc == 2 and len(err) == 1 and match in err[0], err
    assert not (tmp_path / "ds").exists()


def test_distill_targets_a_residual_beacon_at_its_own_unwrapped_phase():
    """A closed-loop sample's target is its received phase (a smooth phase: unwrapping returns it), an open-loop
    sample's the teacher's: the loss is 0 for an estimate equal to each (up to piston)."""
    from metadesign.reconstruction.losses import LOSSES
    from metadesign.reconstruction.model import aperture_mask

    n = 9
    ap = torch.tensor(aperture_mask(n), dtype=torch.float32)
    y, x = np.mgrid[:n, :n] / n
    smooth = torch.tensor(2.5 * x + 1.5 * y ** 2, dtype=torch.float32)  # > pi across: wraps
    teacher_out = torch.randn(1, n, n)

    class Ctx:
        device = "cpu"
        targets: dict = {}
        teacher = staticmethod(lambda p: teacher_out[: len(p)])
        pib = type("P", (), {"ap": ap})()

    rec = torch.stack([torch.ones(n, n, dtype=torch.complex64), torch.polar(torch.ones(n, n), smooth)])
    b = {"index": torch.tensor([3, 4]), "psf": torch.zeros(2, 8, 4, 4), "loop_gain": torch.tensor([0.0, 0.7])}
    phi = torch.stack([teacher_out[0] + 0.3, smooth - 1.0])
    assert float(LOSSES["distill"].fn(Ctx, phi, b, rec)[0]) < 1e-8
    phi_bad = torch.stack([teacher_out[0], torch.zeros(n, n)])  # the residual left uncorrected: a positive loss
    assert float(LOSSES["distill"].fn(Ctx, phi_bad, b, rec)[0]) > 0.05
