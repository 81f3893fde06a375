"""The estimator registry: a new wavefront estimator is one class and one decorator, and the comparison
runs it on the same samples as every other; its rows are checked against independent references (a
zero phase is the uncorrected beam, the received phase is the phase conjugate)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")


@pytest.fixture
def extra_estimators():
    from metadesign.reconstruction.estimators import ESTIMATORS, Estimator, register

    @register
    class Zero(Estimator):
        name, label = "zero", "zero phase"

        def estimate(self, batch, done=None, on_checkpoint=None):
            a = self.device.crop.size
            return torch.zeros((len(batch["psf"]), a, a))

    @register
    class Oracle(Estimator):
        name, label = "oracle", "received phase"

        def estimate(self, batch, done=None, on_checkpoint=None):
            rec = torch.from_numpy(batch["received"])
            return torch.angle(rec) * torch.from_numpy(self.device.crop.aperture_mask())

    yield
    for k in ("zero", "oracle"):
        ESTIMATORS.pop(k, None)


def test_a_registered_estimator_runs_in_the_comparison(extra_estimators, tiny_dataset, tmp_path):
    from metadesign.studies.compare import CompareSettings, run_compare, summarise, write_compare

    st = CompareSettings(split="train", limit=6, batch=4, methods=("zero", "oracle", "shack_hartmann"),
                         latency_samples=1)
    res = run_compare(None, tiny_dataset, st)
    rows = res["rows"]
    assert np.array_equal(rows["zero"], rows["none"])
    assert np.allclose(rows["oracle"], rows["phase_conjugate"], rtol=1e-6)
    assert {"zero", "oracle", "shack_hartmann"} <= set(res["latency_ms"])
    summ = summarise(res)
    assert summ["npib"]["oracle"] > summ["npib"]["zero"]
    files = write_compare(res, tmp_path / "cmp")
    assert (tmp_path / "cmp" / "compare.png").exists() and len(files) >= 3
    header = (tmp_path / "cmp" / "compare.csv").read_text().splitlines()[0].split(",")
    assert header[3:] == ["none", "shack_hartmann", "zero", "oracle", "phase_conjugate", "complex_conjugate"]


def test_registry_names_are_unique_and_complete():
    from metadesign.reconstruction.estimators import ESTIMATORS, Estimator, make_estimator, register

    assert list(ESTIMATORS)[:4] == ["shack_hartmann", "retrieval", "unet", "hybrid"]

    class Dup(Estimator):
        name = "unet"

    with pytest.raises(ValueError):
        register(Dup)
    from metadesign.validation import ValidationError

    with pytest.raises(ValidationError, match="expected one of"):
        make_estimator("nope", None)
