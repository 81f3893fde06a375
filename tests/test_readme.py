"""The Python blocks of the README and of the documentation's guide pages run (the API they show exists
and works), on the test session's small products in place of the paper-scale ones they name (same code,
smaller files).  The gallery examples run when the docs build (``make docs``, in CI)."""

import re

import pytest
from conftest import REPO, tiny_dataset_recipe, tiny_model

torch = pytest.importorskip("torch")


PAGES = [REPO / "README.md", *sorted(p for p in (REPO / "docs").rglob("*.md") if not {"_build", "gallery"} & set(p.parts))]


def _python_blocks() -> list[str]:
    return [b for page in PAGES for b in re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S)]


def test_readme_has_python_blocks():
    assert len(_python_blocks()) >= 2


@pytest.mark.parametrize("i", range(len(_python_blocks())))
def test_readme_python_block_runs(i, demo_products, tmp_path, monkeypatch):
    from metadesign.reconstruction import build_dataset, load_dataset_recipe

    code = _python_blocks()[i]
    model = tiny_model(tmp_path)  # a U-Net for the small dataset's 8 x 16^2 tensors
    ds = tmp_path / "ds"
    if "dataset-demo" in code:  # 8 samples with a test split, on the demo layout
        build_dataset(load_dataset_recipe(tiny_dataset_recipe(tmp_path, demo_products["layout"], samples=8,
                                                              extra="split = [0.5, 0.25, 0.25]\n")), ds)
    for big, small in {"layouts/paper-5mm/layout.oas": demo_products["layout"],
                       "layouts/paper-5mm": demo_products["design"],
                       "sensing/paper.toml": REPO / "sensing" / "demo.toml",
                       "sensing/turbulence.toml": REPO / "sensing" / "turbulence.toml",
                       "sensing/models/demo-unet-long.safetensors": model,
                       "sensing/dataset-demo": ds}.items():
        code = code.replace(f'"{big}"', repr(str(small)))
    code = code.replace('"library/', '"' + str(REPO / "library") + "/")  # the committed library products
    assert "paper-5mm" not in code and "dataset-demo" not in code, code
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"documentation python block {i}", "exec"), {})
