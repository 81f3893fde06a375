"""Test setup: one BLAS/OpenMP thread per process (the CI machine has 2 shared cores)."""

import os

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_k] = "1"

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

# a plugin may have loaded numpy (and its BLAS, with one thread per core) before the variables above
threadpool_limits(1)

REPO = Path(__file__).resolve().parents[1]

def leb128(v: int) -> bytes:
    """The OASIS unsigned integer, written out from the standard's definition (a test reference)."""
    out = []
    while True:
        out.append((v & 0x7F) | (0x80 if v >> 7 else 0))
        v >>= 7
        if not v:
            return bytes(out)


#: a small circular design (0.2 mm, ~285 cells a side) for the tiled layout tests
SMALL_TILED_RECIPE = """
[design]
library = "{lib}"
wavelength_nm = 1550.0
period_um = 0.7
aperture_mm = 0.2
clear_aperture = "circle"
[discretizer]
tile_rows = 16
"""

#: the checkout's product folders: no test may leave anything new in them (tests write to tmp_path)
PRODUCT_FOLDERS = ("library", "layouts", "sensing")


def _product_tree() -> set:
    return {str(p.relative_to(REPO)) for f in PRODUCT_FOLDERS for p in (REPO / f).iterdir()}


def pytest_sessionstart(session):
    if not hasattr(session.config, "workerinput"):  # the controller (xdist) or the only process
        session.config._products_before = _product_tree()


def pytest_sessionfinish(session, exitstatus):
    before = getattr(session.config, "_products_before", None)
    if before is None:
        return
    new = sorted(_product_tree() - before)
    if new:
        session.config.get_terminal_writer().line(
            f"\ntests left {len(new)} new entries in the checkout's product folders: {', '.join(new[:8])}", red=True)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(scope="session")
def paper_library():
    from metadesign.library import load_library

    return load_library(REPO / "library" / "paper.npz")


def run_cli(*args, cwd=None):
    """Run ``python -m metadesign ARGS`` in a subprocess; returns CompletedProcess."""
    import subprocess

    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run([sys.executable, "-m", "metadesign", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, env=env, timeout=600)


def run_main(argv, capsys):
    """``metadesign ARGV`` in-process: (exit status, stdout, non-empty stderr lines)."""
    from metadesign.cli import main

    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse errors
        rc = exc.code
    cap = capsys.readouterr()
    return rc, cap.out, [x for x in cap.err.splitlines() if x.strip()]


try:  # torch: one thread per process, like the workers
    import torch  # noqa: E402

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover
    pass


@pytest.fixture(scope="session")
def demo_products(tmp_path_factory):
    """The demo design and its OASIS layout, built once per test session (read-only for tests)."""
    from metadesign.design.recipe import load_design_recipe
    from metadesign.design.store import run_design
    from metadesign.layouts import write_layout

    base = tmp_path_factory.mktemp("demo-products")
    d, out = run_design(load_design_recipe(REPO / "layouts" / "demo.toml"), base / "design")
    from metadesign.design.store import load_design

    write_layout(load_design(out), out / "layout.oas", "oas")
    return {"design": out, "layout": out / "layout.oas", "sensor": REPO / "sensing" / "demo.toml"}


def tiny_dataset_recipe(folder: Path, layout: Path, samples: int = 12, shard: int = 4, tensor: int = 16,
                        extra: str = "") -> Path:
    """A tiny dataset recipe on the demo layout (machinery tests; stage-6 data uses the paper layout)."""
    p = Path(folder) / "tiny.toml"
    p.write_text(f"""[dataset]
layout = "{layout}"
sensor = "{REPO / 'sensing' / 'demo.toml'}"
turbulence = "{REPO / 'sensing' / 'turbulence.toml'}"
samples = {samples}
tensor_size = {tensor}
shard_size = {shard}
seed = 5
{extra}""")
    return p


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory, demo_products):
    from metadesign.reconstruction.dataset import build_dataset, load_dataset_recipe

    base = tmp_path_factory.mktemp("tiny-dataset")
    rec = load_dataset_recipe(tiny_dataset_recipe(base, demo_products["layout"]))
    build_dataset(rec, base / "ds", workers=1)
    return base / "ds"


def tiny_model(folder: Path) -> Path:
    """An untrained toy U-Net for 8 x 16^2 inputs (``m.safetensors``) and a training recipe matching it
    (``t.toml``) in ``folder``: the machinery tests of tolerance, transfer and the LPA check."""
    import torch

    from metadesign.reconstruction.model import UNetConfig, build_unet, save_model

    torch.manual_seed(0)
    save_model(build_unet(UNetConfig(base=4, depth=3, input_size=16)), Path(folder) / "m.safetensors",
               {"noise_percent": 0})
    (Path(folder) / "t.toml").write_text("[model]\nbase = 4\ndepth = 3\n[train]\nbatch = 4\n")
    return Path(folder) / "m.safetensors"
