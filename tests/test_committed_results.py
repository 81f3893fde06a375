"""Committed study results match the recipes and models they name (issue #32): each result's ``made_with``
block (metadesign.studies.madewith) records the model's weights sha256 and the dataset recipe's declared
key; a result whose model or dataset no longer matches its recipe (a retrained model, an edited recipe)
fails here until it is re-run."""

import json

import pytest
from conftest import REPO

from metadesign.config import load_toml
from metadesign.reconstruction.dataset import dataset_recipe_from_dict, load_dataset_recipe
from metadesign.tasks import content_key, file_key

SENSING = REPO / "sensing"

#: committed result -> (its recipe, the key of the result file); compare results are made by a command,
#: not a recipe: their model is checked against the committed file of that name and their dataset
#: against the dataset recipe of that name
STUDIES = {
    "tolerance-demo-out/tolerance.json": "tolerance-demo.toml",
    "tolerance-coupling-out/tolerance.json": "tolerance-coupling.toml",
    "transfer-demo-out/transfer.json": "transfer-demo.toml",
    "tolerance-codesign-out/tolerance.json": "tolerance-codesign.toml",
    "tolerance-codesign-paper-out/tolerance.json": "tolerance-codesign-paper.toml",
    "tolerance-codesign-wide-out/tolerance.json": "tolerance-codesign-wide.toml",
}
COMPARES = ["compare-demo/compare.json", "compare-demo-refine/compare.json"]


def _made_with(result: str) -> dict:
    doc = json.loads((SENSING / result).read_text())
    mw = doc.get("made_with")
    assert mw, f"sensing/{result}: no made_with block (made before results recorded what made them: re-run it)"
    return mw


@pytest.mark.parametrize("result, recipe", sorted(STUDIES.items()))
def test_a_committed_study_matches_its_recipe_and_model(result, recipe):
    mw = _made_with(result)
    raw = load_toml(SENSING / recipe)
    model = SENSING / raw["evaluate"]["model"]
    assert mw["model"]["weights_sha256"] == file_key(model), \
        f"sensing/{result} was made with another model than {model.name} (its recipe's): re-run it"
    # the study's dataset: its [dataset] (and, for a transfer study, the device as made: [fabrication])
    ds = dataset_recipe_from_dict({k: raw[k] for k in ("dataset", "fabrication") if k in raw}, "check",
                                  SENSING / recipe)
    assert mw["dataset"]["recipe_key"] == ds.declared_key(), \
        f"sensing/{result}: its recipe's [dataset] (or the recipes it names) changed since: re-run it"
    assert mw["recipe"]["key"] == content_key(raw), f"sensing/{result}: sensing/{recipe} changed since: re-run it"


@pytest.mark.parametrize("result", COMPARES)
def test_a_committed_comparison_matches_the_model_and_dataset_it_names(result):
    mw = _made_with(result)
    model = SENSING / "models" / mw["model"]["name"]
    assert model.is_file(), f"sensing/{result}: made with {model.name}, which is not committed"
    assert mw["model"]["weights_sha256"] == file_key(model), f"sensing/{result}: {model.name} changed since: re-run it"
    ds = load_dataset_recipe(SENSING / f"{mw['dataset']['name']}.toml")
    assert mw["dataset"]["recipe_key"] == ds.declared_key(), \
        f"sensing/{result}: sensing/{mw['dataset']['name']}.toml changed since: re-run it"


def test_the_declared_key_follows_content_not_comments(tmp_path):
    """The check above can fail: an edited value changes the key, a comment does not."""
    src = (SENSING / "dataset-demo.toml").read_text()
    (tmp_path / "sensing").mkdir()
    for f in ("paper.toml", "turbulence.toml"):
        (tmp_path / "sensing" / f).write_text((SENSING / f).read_text())
    a = tmp_path / "sensing" / "a.toml"
    a.write_text(src)
    k0 = load_dataset_recipe(a).declared_key()
    a.write_text("# a comment\n" + src)
    assert load_dataset_recipe(a).declared_key() == k0
    a.write_text(src.replace("seed = 0", "seed = 7"))
    assert load_dataset_recipe(a).declared_key() != k0
    (tmp_path / "sensing" / "turbulence.toml").write_text((SENSING / "turbulence.toml").read_text() + "\n\n")
    a.write_text(src)
    assert load_dataset_recipe(a).declared_key() == k0  # whitespace in a named recipe: the same content


def test_the_committed_peds_model_matches_its_table_library_and_report():
    """library/paper-peds.json: calibrated against the committed library (its sha256), on the committed
    converged table (its sha256), and the model is what its report chose (levels) and fitted last."""
    import numpy as np

    from metadesign.library.locate import file_sha256
    from metadesign.library.peds import load_peds
    from metadesign.library.store import load_library

    lib = load_library(REPO / "library" / "paper.npz")
    m = load_peds(REPO / "library" / "paper-peds.json", lib)  # refuses another library
    cert = m.card["certification"]
    assert m.card["table"]["sha256"] == file_sha256(REPO / "library" / m.card["table"]["path"])
    chosen = [lv["requested"] for lv in cert["levels"] if lv.get("chosen", True)]
    assert list(m.harmonics) == chosen
    np.testing.assert_allclose(np.array(m.coef), [complex(*c) for c in cert["learning_curve"][-1]["coef"]])
    assert (REPO / "library" / m.card["figure"]).is_file()


#: committed loop reports whose provenance names their recipe and files (the reports before provenance,
#: loop-demo-out and loop-demo-gain-out, name none)
LOOPS = sorted(p.relative_to(SENSING).as_posix() for p in SENSING.glob("*-out/loop.json")
               if json.loads(p.read_text()).get("provenance"))


@pytest.mark.parametrize("result", LOOPS)
def test_a_committed_loop_report_matches_its_recipe_and_files(result):
    """A loop report's recipe (by its parsed content: a comment edit keeps it) and every file it names (the
    device's recipes, the models and their cards, by their bytes) are still what made it."""
    report = SENSING / result
    pv = json.loads(report.read_text())["provenance"]
    recipe = (report.parent / pv["recipe"]["path"]).resolve()
    assert content_key(load_toml(recipe)) == pv["recipe"]["key"], \
        f"sensing/{result}: {recipe.name} changed since it was made: re-run it"
    for name in ("design", "sensor", "turbulence", "model", "realtime"):
        entry = pv.get(name)
        for e in ([entry, entry.get("card")] if entry and "card" in entry else [entry]):
            if e and e["sha256"]:
                assert file_key(recipe.parent / e["path"]) == e["sha256"], \
                    f"sensing/{result}: {e['path']} changed since it was made: re-run it"


def test_the_loop_reports_are_checked():
    assert "loop-demo-w48-out/loop.json" in LOOPS  # the headline's report is among them
