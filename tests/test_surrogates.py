"""The supercell surrogate protocol (metadesign.library.surrogates): every model (the LPA, the coupling
network, PEDS) satisfies it and equals the kernel it wraps (lpa_t, coupling_t, certified_t; the torch twins
their numpy values); the resolver finds models by name and by file and refuses the wrong kind in one line;
a PEDS model round-trips through cards.py and the committed one loads unchanged; the device's forward model
takes the models by name (peds refused in one line: a whole device cannot afford it)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from metadesign.cards import card_format, read_card
from metadesign.library.coupling import lpa_t, relative_error
from metadesign.library.peds import PEDS_FORMAT, PedsModel, certified_t, load_peds, save_peds
from metadesign.library.store import interpolate_t
from metadesign.library.surrogates import LPA, PEDS, CouplingNet, SupercellSurrogate, surrogate
from metadesign.validation import ConfigError, ValidationError

LEVELS = (25, 41)  # tiny truncations: cheap solves
COEF = (0.3 - 0.7j, 1.2 + 0.4j)
COUPLING = "library/paper-coupling.safetensors"


def _widths(n, seed=0):
    return np.random.default_rng(seed).uniform(0.15e-6, 0.45e-6, size=(n, 2, 2, 2))


def _one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, msg
    return msg


@pytest.fixture(scope="module")
def net(paper_library, repo):
    pytest.importorskip("torch")
    return CouplingNet(paper_library, repo / COUPLING)


@pytest.fixture(scope="module")
def peds(paper_library):
    return PEDS(paper_library, model=PedsModel(LEVELS, COEF, paper_library.identity))


def test_every_model_satisfies_the_protocol(paper_library, net, peds):
    for s, name in ((LPA(paper_library), "lpa"), (net, "coupling"), (peds, "peds")):
        assert isinstance(s, SupercellSurrogate) and s.name == name
        card = s.card()
        assert card["surrogate"] == name and card["library_sha256"] == paper_library.identity
        assert "certification" in card and card["description"]
    assert net.card()["model"]["weights_sha256"] == net.file_card["weights_sha256"]
    assert net.card()["certification"]["held_out_supercells"] == 250
    assert peds.card()["model"]["harmonics"] == list(LEVELS)


def test_lpa_is_lpa_t_and_its_twin(paper_library):
    torch = pytest.importorskip("torch")
    w = _widths(5, 1)
    tu = interpolate_t(paper_library, w[..., 0], w[..., 1])[0]
    s = LPA(paper_library)
    np.testing.assert_array_equal(s.t(w), lpa_t(tu))
    np.testing.assert_array_equal(s.t(w, 2 * tu), lpa_t(2 * tu))
    np.testing.assert_allclose(s.t_torch(torch.tensor(w)).numpy(), s.t(w), atol=1e-6)
    assert not s.pillar_terms(w).any()


def test_coupling_net_is_coupling_t(paper_library, net):
    torch = pytest.importorskip("torch")
    from metadesign.library.coupling_net import coupling_t

    w = _widths(6, 2)
    tu = interpolate_t(paper_library, w[..., 0], w[..., 1])[0]
    np.testing.assert_array_equal(net.t(w), coupling_t(net.model, w))
    np.testing.assert_array_equal(net.t(w, tu), coupling_t(net.model, w, tu))
    np.testing.assert_allclose((tu + net.pillar_terms(w)).mean((1, 2)), net.t(w, tu), atol=1e-6)
    with torch.no_grad():
        np.testing.assert_allclose(net.t_torch(torch.tensor(w)).numpy(), net.t(w), atol=1e-6)
        np.testing.assert_allclose(net.t_torch(torch.tensor(w), torch.tensor(tu)).numpy(), net.t(w, tu), atol=1e-6)


def test_peds_is_certified_t(paper_library, peds, tmp_path):
    w = _widths(2, 3)
    ref = certified_t(paper_library, w, tmp_path / "p", peds.model)
    np.testing.assert_array_equal(peds.t(w), ref)  # a temporary scratch folder, removed after
    kept = PEDS(paper_library, model=peds.model, partial=tmp_path / "q")
    np.testing.assert_array_equal(kept.t(w), ref)
    assert (tmp_path / "q").is_dir()
    with pytest.raises(ValidationError) as e:
        peds.pillar_terms(w)
    assert "coupling-check --certified" in _one_line(e)


def test_certify_uses_the_projects_metric(paper_library, net):
    w = _widths(20, 4)
    tu = interpolate_t(paper_library, w[..., 0], w[..., 1])[0]
    lpa = LPA(paper_library)
    t_ref = net.t(w)
    rep = lpa.certify(w, t_ref)
    e = relative_error(lpa.t(w), t_ref, tu)
    assert rep["supercells"] == 20 and rep["surrogate"] == "lpa"
    np.testing.assert_allclose(rep["mean"], e.mean(0))
    np.testing.assert_allclose(rep["p90"], np.percentile(e, 90, 0))
    assert rep["p90_both"] == pytest.approx(np.percentile(e, 90)) and rep["mean_both"] == pytest.approx(e.mean())
    assert net.certify(w, t_ref)["max"] == [0.0, 0.0]
    with pytest.raises(ValidationError) as exc:
        lpa.certify(w, t_ref[:3])
    _one_line(exc)


def test_the_resolver(paper_library, repo, net):
    assert isinstance(surrogate("lpa", paper_library), LPA)
    for name in ("coupling", "supercell"):
        s = surrogate(name, paper_library)
        assert isinstance(s, CouplingNet) and s.file_card["weights_sha256"] == net.file_card["weights_sha256"]
    p = surrogate("peds", paper_library)
    assert isinstance(p, PEDS) and p.path.name == "paper-peds.json"
    for f in (repo / COUPLING, repo / (COUPLING + ".json")):
        assert isinstance(surrogate(f, paper_library), CouplingNet)
    assert isinstance(surrogate(repo / "library/paper-peds.json", paper_library, kind="peds"), PEDS)
    assert surrogate(net, paper_library) is net
    bad = [(("nonsense", paper_library), {}, "expected one of 'lpa', 'coupling', 'peds', 'supercell'"),
           ((repo / "library/paper-peds.json", paper_library), {"kind": "supercell"}, "not a coupling model"),
           ((repo / COUPLING, paper_library), {"kind": "peds"}, "not a peds model"),
           (("lpa", paper_library), {"kind": "coupling"}, "not a coupling model"),
           ((repo / "library/paper.npz", paper_library), {}, "not a metadesign supercell model"),
           ((repo / "sensing/models/codesign-demo-unet.safetensors", paper_library), {}, "not a supercell model")]
    for args, kw, msg in bad:
        with pytest.raises(ValidationError) as e:
            surrogate(*args, **kw)
        assert msg in _one_line(e)


def test_peds_card_round_trips_through_cards(paper_library, repo, tmp_path):
    m = PedsModel(LEVELS, COEF, paper_library.identity,
                  {"certification": {"model": {"mean": [0.1, 0.2]}}, "table": {"path": "t.npz", "sha256": "ab"}})
    p = save_peds(tmp_path / "m.json", m)
    path, cp, card = read_card(p, PEDS_FORMAT, "PEDS supercell model")
    assert path == cp == p and card["format"] == PEDS_FORMAT and card_format(p) == PEDS_FORMAT
    assert card["trained_on"] == {"path": "t.npz", "sha256": "ab"} and list(card)[:4] == [
        "format", "harmonics", "coef", "library"]
    back = load_peds(p, paper_library)
    assert back == m and back.card["certification"] == m.card["certification"]
    assert save_peds(tmp_path / "again.json", back).read_bytes() == p.read_bytes()
    with pytest.raises(ValidationError) as e:
        read_card(p, "metadesign.coupling/1", "coupling model")
    assert "expected metadesign.coupling/1" in _one_line(e)
    committed = repo / "library/paper-peds.json"  # written before trained_on: read unchanged
    raw = json.loads(committed.read_text())
    got = load_peds(committed, paper_library)
    assert got.harmonics == tuple(raw["harmonics"]) and got.coef == tuple(complex(a, b) for a, b in raw["coef"])
    assert PEDS(paper_library, committed).card()["model"]["trained_on"] == raw["table"]


def test_the_device_takes_the_models_by_name(paper_library, net):
    from metadesign.sensing.model import AsFabricated, sensing_from_dict
    from metadesign.sensing.transmission import Perturbation, pillar_transmission

    for value, kept in (("lpa", "lpa"), ("supercell", "supercell"), ("coupling", "supercell"), ("peds", "peds")):
        assert sensing_from_dict({"pupil": {"coupling": value}}).coupling == kept
    with pytest.raises(ConfigError) as e:
        sensing_from_dict({"pupil": {"coupling": "pds"}})
    assert _one_line(e).startswith("pupil.coupling: expected one of 'lpa', 'supercell', 'coupling', 'peds'")
    fab = AsFabricated(None, paper_library, paper_library.period, paper_library.wavelength, 2, ((), ()))
    for name in ("supercell", "coupling", net):
        fc = fab.with_coupling(name)
        assert fc.coupling_name == "supercell" and isinstance(fc.surrogate, CouplingNet)
        assert fc.coupling_card["weights_sha256"] == net.file_card["weights_sha256"]
    assert fab.with_coupling("lpa").coupling is None and fab.with_coupling(LPA(paper_library)).coupling_name == "lpa"
    for bad in ("peds", "pds"):
        with pytest.raises(ConfigError) as e:
            fab.with_coupling(bad)
        assert _one_line(e).startswith("pupil.coupling: ")
    # the pupil's pillars under a surrogate: the network's own numbers; the LPA's; PEDS refused
    rng = np.random.default_rng(5)
    im = rng.integers(0, 6, (6, 8)).astype(np.int32)
    im[0, 0] = -1
    atoms = rng.integers(150, 450, (6, 2))
    for pert in (Perturbation(), Perturbation(jitter=3e-9, seed=2)):
        ref = pillar_transmission(im, atoms, paper_library, pert, coupling=net.model)
        got = pillar_transmission(im, atoms, paper_library, pert, coupling=net)
        np.testing.assert_array_equal(got[0], ref[0])
        lpa = pillar_transmission(im, atoms, paper_library, pert, coupling=LPA(paper_library))
        np.testing.assert_array_equal(lpa[0], pillar_transmission(im, atoms, paper_library, pert)[0])
    with pytest.raises(ValidationError) as e:
        pillar_transmission(im, atoms, paper_library, coupling=PEDS(paper_library, model=PedsModel(LEVELS, COEF)))
    _one_line(e)
