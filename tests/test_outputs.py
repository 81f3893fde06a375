"""The product layer (metadesign.outputs), table-driven over every command that writes.

Each command meets the outputs that must never be written: its own input, a path inside an input, a
folder around an input, a user's file, a user's folder (with a dot-file), another kind of product, and an
output another process is writing.  Each must exit 2 with one line on stderr and leave every tree
byte-identical.  Then: the kinds are recognised from the files themselves, a resource estimate refuses
with its figures, the CLI cannot write around the layer, and the issue's four data-loss cases."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, run_main, tiny_model

LIB = REPO / "library" / "paper.npz"


def _tree(root: Path) -> dict:
    """Every file (with its bytes' sha256) and folder under ``root``."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        out[rel] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, demo_products, tiny_dataset):
    """Small copies of every kind of input, in one folder (copied per case)."""
    base = tmp_path_factory.mktemp("product-inputs")
    shutil.copy(LIB, base / "lib.npz")
    shutil.copy(REPO / "library" / "paper.toml", base / "lib.toml")
    (base / "lib.toml").write_text((base / "lib.toml").read_text())
    shutil.copytree(demo_products["design"], base / "design")
    shutil.copytree(tiny_dataset, base / "ds")
    m = base / "models"
    m.mkdir()
    tiny_model(m)
    shutil.copy(REPO / "library" / "paper-supercells.npz", base / "table.npz")
    for f in ("paper-coupling.safetensors", "paper-coupling.safetensors.json"):
        shutil.copy(REPO / "library" / f, base / f)
    dr = (REPO / "layouts" / "demo.toml").read_text()
    (base / "demo.toml").write_text(dr.replace('library = "../library/paper.npz"', f'library = "{base / "lib.npz"}"'))
    (base / "scenario.toml").write_text((REPO / "sensing" / "turbulence.toml").read_text())
    (base / "sc.toml").write_text(
        (REPO / "library" / "paper-supercells.toml").read_text().replace('"paper.npz"', f'"{base / "lib.npz"}"')
        .replace('"../layouts/paper-5mm.toml"', f'"{base / "demo.toml"}"')
        .replace('"../layouts/demo.toml"', f'"{base / "demo.toml"}"'))
    caps = base / "caps"
    caps.mkdir()
    (caps / "manifest.csv").write_text("sample,frame_x,frame_y,slm_phase\n")
    (caps / "flat.csv").write_text("frame_x,frame_y\n")
    (base / "p.toml").write_text(f"""[pipeline]
library = "{base / 'lib.npz'}"
design = "{base / 'demo.toml'}"
sensor = "{REPO / 'sensing' / 'demo.toml'}"
turbulence = "{base / 'scenario.toml'}"
[dataset]
samples = 16
tensor_size = 16
[train]
model = "{base / 'models' / 'm.safetensors'}"
""")
    (base / "cd").mkdir()  # a co-design run's diversity: the device as built
    (base / "cd" / "diversity.json").write_text(json.dumps({
        "focal_length_mm": [[4.88, 4.92, 4.96, 5.0], [5.04, 5.08, 5.12, 5.16]], "zernike_noll": [5],
        "zernike_rad": [[[0.0]] * 4, [[0.0]] * 4]}))
    (base / "s2.toml").write_text(f'[dataset]\nlayout = "{base / "design" / "layout.oas"}"\n')
    (base / "tiny.toml").write_text(
        f'[dataset]\nlayout = "{base / "design" / "layout.oas"}"\nsensor = "{REPO / "sensing" / "demo.toml"}"\n'
        f'turbulence = "{base / "scenario.toml"}"\nsamples = 4\ntensor_size = 16\nshard_size = 4\nseed = 5\n')
    return base


# command -> (argv with {OUT} for the output and {IN} for the folder of inputs, output is a folder?,
#             the input that the "is / inside / around an input" cases use, relative to {IN})
COMMANDS = {
    "library build": (["library", "build", "{IN}/lib.toml", "-o", "{OUT}.npz"], False, "lib.toml"),
    "library plot": (["library", "plot", "--library", "{IN}/lib.npz", "-o", "{OUT}.png"], False, "lib.npz"),
    "library export": (["library", "export", "--library", "{IN}/lib.npz", "-o", "{OUT}.csv"], False, "lib.npz"),
    "library coupling": (["library", "coupling", "{IN}/table.npz", "--library", "{IN}/lib.npz", "-o",
                          "{OUT}.safetensors"], False, "table.npz"),
    "design build": (["design", "build", "{IN}/demo.toml", "-o", "{OUT}"], True, "demo.toml"),
    "design plot": (["design", "plot", "{IN}/design", "-o", "{OUT}.png"], False, "design/design.npz"),
    "design compensate": (["design", "compensate", "{IN}/design", "--coupling-model",
                           "{IN}/paper-coupling.safetensors", "-o", "{OUT}"], True, "design/design.npz"),
    "layout write": (["layout", "write", "{IN}/design", "-o", "{OUT}.oas"], False, "design/design.npz"),
    "layout tiled": (["layout", "tiled", "{IN}/demo.toml", "-o", "{OUT}"], True, "demo.toml"),
    "layout preview": (["layout", "preview", "{IN}/design/layout.oas", "-o", "{OUT}.png"], False,
                       "design/layout.oas"),
    "psf": (["psf", "{IN}/design/layout.oas", "--sensor", str(REPO / "sensing" / "demo.toml"), "-o", "{OUT}"], True,
            "design/layout.oas"),
    "fab-study": (["fab-study", "{IN}/design/layout.oas", "-o", "{OUT}"], True, "design/layout.oas"),
    "phasemap": (["phasemap", "{IN}/design/layout.oas", "-o", "{OUT}"], True, "design/layout.oas"),
    "turbulence validate": (["turbulence", "validate", "{IN}/scenario.toml", "--samples", "2", "-o", "{OUT}"], True,
                            "scenario.toml"),
    "dataset build": (["dataset", "build", "{IN}/tiny.toml", "-o", "{OUT}"], True, "tiny.toml"),
    "dataset plot": (["dataset", "plot", "{IN}/ds", "-o", "{OUT}.png"], False, "ds/psf"),
    "dataset synth-captures": (["dataset", "synth-captures", "{IN}/ds", "--device", "{IN}/ds", "-o", "{OUT}"],
                               True, "ds/psf"),
    "train": (["train", "{IN}/models/t.toml", "--dataset", "{IN}/ds", "-o", "{OUT}"], True, "ds/psf"),
    "evaluate": (["evaluate", "{IN}/models/m.safetensors", "{IN}/ds", "-o", "{OUT}"], True, "ds/psf"),
    "export": (["export", "{IN}/models/m.safetensors", "-o", "{OUT}.onnx"], False, "models/m.safetensors"),
    "compare": (["compare", "{IN}/models/m.safetensors", "{IN}/ds", "-o", "{OUT}"], True, "ds/psf"),
    "lpa-check": (["library", "lpa-check", "{IN}/design", "-o", "{OUT}"], True, "design/design.npz"),
    "demo": (["demo", "-o", "{OUT}"], True, None),
    "library supercells": (["library", "supercells", "{IN}/sc.toml", "-o", "{OUT}.npz"], False, "sc.toml"),
    "coupling-check": (["library", "coupling-check", "{IN}/design", "--coupling-model",
                        "{IN}/paper-coupling.safetensors", "-o", "{OUT}"], True, "design/design.npz"),
    "retrieve": (["retrieve", "NONE", "{IN}/ds", "-o", "{OUT}"], True, "ds/psf"),
    "run": (["run", "{IN}/p.toml", "-o", "{OUT}"], True, "p.toml"),
    "table-s2": (["table-s2", "{IN}/s2.toml", "-o", "{OUT}"], True, "s2.toml"),
    "codesign": (["codesign", "{IN}/cd", "--dataset", "{IN}/ds", "--base", "{IN}/demo.toml", "--modes", "3",
                  "--fisher-samples", "0", "--random", "0", "-o", "{OUT}"], True, "cd/diversity.json"),
    "dataset import": (["dataset", "import", "{IN}/caps", "--calibration", "{IN}/caps/flat.csv", "--reference",
                        "{IN}/ds", "-o", "{OUT}"], True, "caps/manifest.csv"),
}

CASES = ["is-input", "inside-input", "around-input", "user-file", "user-folder", "other-kind", "concurrent"]


def _argv(cmd, base: Path, out: Path) -> list[str]:
    return [a.replace("{IN}", str(base)).replace("{OUT}", str(out)) for a in COMMANDS[cmd][0]]


def _out_of(argv: list[str], placeholder: Path) -> Path:
    """The output path in ``argv`` (the argument that starts with the placeholder)."""
    return Path(next(a for a in argv if a.startswith(str(placeholder))))


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("cmd", list(COMMANDS))
def test_every_writer_refuses_what_it_must_not_write(cmd, case, inputs, tmp_path, capsys):
    base = tmp_path / "in"
    shutil.copytree(inputs, base)
    folder_out, inp = COMMANDS[cmd][1], COMMANDS[cmd][2]
    ph = tmp_path / "work" / "out"
    ph.parent.mkdir()
    argv = _argv(cmd, base, ph)
    out = _out_of(argv, ph)
    if case in ("is-input", "inside-input", "around-input"):
        if inp is None:
            pytest.skip("the demo reads only packaged products")
        src = base / inp
        target = {"is-input": src, "inside-input": src / "x" if src.is_dir() else src.parent / src.name / "x",
                  "around-input": src.parent}[case]
        if case == "inside-input" and not src.is_dir():
            target = src  # a file has no inside: the same as the input itself
        argv = [str(target) if a == str(out) else a for a in argv]
        out = target
    elif case == "user-file":
        out.write_text("a user's notes\n")
    elif case == "user-folder":
        if not folder_out:
            out.write_bytes(b"\x89PNG\r\n\x1a\nnot ours" if out.suffix == ".png" else b"user data")
        else:
            out.mkdir()
            (out / ".settings").write_text("mine")
            (out / "metrics.json").write_text("{}")
    elif case == "other-kind":
        if folder_out:
            out.mkdir()
            kind = "psf" if "psf" not in cmd else "dataset"
            (out / ".metadesign.json").write_text('{"format": "metadesign.product/1", "kind": "%s"}' % kind)
            (out / "result.txt").write_text("kept")
        elif out.suffix == ".npz":  # a supercell table where a library goes, and the other way round
            shutil.copy(base / ("lib.npz" if cmd == "library supercells" else "table.npz"), out)
        elif out.suffix == ".png":
            pytest.skip("no other kind of product is a PNG")
        else:
            shutil.copy(base / "lib.npz", out)  # a library under a foreign suffix
    before = {"in": _tree(base), "work": _tree(ph.parent)}
    fd = None
    if case == "concurrent":
        from metadesign.io import lock_path

        fd = os.open(lock_path(out), os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        before["work"] = _tree(ph.parent)
    try:
        rc, stdout, err = run_main(argv, capsys)
    finally:
        if fd is not None:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
    assert rc == 2, (cmd, case, rc, err[-3:])
    assert len(err) == 1 and err[0].startswith("metadesign: error:"), (cmd, case, err)
    assert "Traceback" not in "".join(err)
    after = {"in": _tree(base), "work": _tree(ph.parent)}
    assert after == before, (cmd, case, err)


def test_the_issue_data_loss_cases(inputs, tmp_path, capsys):
    """#31: the four commands that replaced what a user had, each with exit 0."""
    base = tmp_path / "in"
    shutil.copytree(inputs, base)
    rec = tmp_path / "sc.toml"
    rec.write_text((REPO / "library" / "paper-supercells.toml").read_text())
    before = _tree(base)
    cases = [
        ["library", "supercells", str(REPO / "library" / "paper-supercells.toml"), "-o", str(base / "lib.npz")],
        ["library", "coupling", str(base / "table.npz"), "--library", str(base / "lib.npz"), "-o",
         str(base / "table.npz")],
        ["design", "compensate", str(base / "design"), "--coupling-model", str(base / "paper-coupling.safetensors"),
         "-o", str(base / "design")],
    ]
    for argv in cases:
        rc, _, err = run_main(argv, capsys)
        assert rc == 2 and len(err) == 1, (argv, err)
    user = base / "mine"
    user.mkdir()
    (user / "metrics.json").write_text('{"my": "results"}')
    before = _tree(base)
    rc, _, err = run_main(["layout", "tiled", str(base / "demo.toml"), "-o", str(user)], capsys)
    assert rc == 2 and "did not write" in err[0]
    assert _tree(base) == before


def test_kinds_are_recognised_from_the_files(tmp_path):
    from metadesign.plotting import pyplot, save_figure
    from metadesign.outputs import identify

    assert identify(LIB) == "unit-cell-library"
    assert identify(REPO / "library" / "paper-supercells.npz") == "supercells"
    assert identify(REPO / "library" / "paper-coupling.safetensors") == "coupling"
    assert identify(REPO / "sensing" / "models" / "demo-unet-robust.safetensors") == "unet"
    assert identify(REPO / "sensing" / "models" / "demo-refine.safetensors") == "refiner"
    assert identify(REPO / "library" / "paper.toml") is None
    # folders written before the marker existed: by their summaries (the committed studies)
    for folder, kind in (("compare-demo", "compare"), ("tolerance-demo-out", "tolerance"),
                         ("transfer-demo-out", "transfer"), ("lpa-check", "lpa-check"),
                         ("coupling-check", "coupling-check")):
        assert identify(REPO / "sensing" / folder) == kind, folder
    plt = pyplot()
    save_figure(plt.figure(), tmp_path / "f.png")
    assert identify(tmp_path / "f.png") == "figure"
    plt.imsave(tmp_path / "g.png", [[0, 1], [1, 0]])  # a PNG metadesign did not write
    assert identify(tmp_path / "g.png") is None
    (tmp_path / "d").mkdir()
    assert identify(tmp_path / "d") is None


def test_a_job_larger_than_the_machine_is_refused_with_its_estimate(tmp_path, capsys):
    """A 300 mm aperture: ~1.8e11 pillars; the estimate names the disk it needs and what is free."""
    rec = tmp_path / "huge.toml"
    txt = (REPO / "layouts" / "wide-25mm.toml").read_text().replace("../library/", str(REPO / "library") + "/")
    import re

    txt = re.sub(r"aperture_mm\s*=\s*[0-9.]+", "aperture_mm = 300.0", txt)
    rec.write_text(txt)
    rc, _, err = run_main(["layout", "tiled", str(rec), "-o", str(tmp_path / "out")], capsys)
    assert rc == 2 and "needs about" in err[0] and "GB of disk" in err[0] and "free" in err[0], err
    assert not (tmp_path / "out").exists()


def test_the_cli_cannot_write_around_the_product_layer(tmp_path):
    """With the CLI's enforcement on, a write outside every declared output is a programming error."""
    from metadesign.io import atomic_write_text, enforce_claims
    from metadesign.outputs import product

    enforce_claims(True)
    try:
        with pytest.raises(RuntimeError, match="outside any declared output"):
            atomic_write_text(tmp_path / "stray.txt", "x")
        with product(tmp_path / "ok", "demo"):
            atomic_write_text(tmp_path / "ok" / "a.txt", "x")
            with pytest.raises(RuntimeError):
                atomic_write_text(tmp_path / "elsewhere.txt", "x")
    finally:
        enforce_claims(False)
    assert not (tmp_path / "stray.txt").exists() and (tmp_path / "ok" / "a.txt").exists()


def test_no_module_writes_files_by_hand():
    """Every file write goes through metadesign.io (atomic, claimed): a static scan for raw writers."""
    import re

    raw = re.compile(r"\.savefig\(|torch\.save\(|np\.save\(|open\([^)]*['\"][wa]b?['\"]|\.write_oas\(|\.write_gds\(")
    allowed = {"io.py", "plotting.py"}
    bad = []
    for p in (REPO / "metadesign").rglob("*.py"):
        if p.name in allowed:
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            # allowed: writing the temporary path atomic_path yields, or an in-memory buffer / its handle
            if raw.search(line) and not re.search(r"atomic|\btmp\b|\bbuf\b|\(fh\b", line):
                bad.append(f"{p.relative_to(REPO)}:{i}: {line.strip()}")
    assert not bad, "\n".join(bad)


def test_products_written_before_their_marks_stay_replaceable(tmp_path):
    """A coupling model vouches for its card and figure; a figure inside a product folder, a run folder
    holding only a torch checkpoint: metadesign's own, replaceable.  The same files elsewhere: refused."""
    import zipfile

    from metadesign.cards import card_path
    from metadesign.outputs import check_output, identify
    from metadesign.validation import InputError

    c = tmp_path / "c.safetensors"
    shutil.copy(REPO / "library" / "paper-coupling.safetensors", c)
    shutil.copy(REPO / "library" / "paper-coupling.safetensors.json", card_path(c))
    shutil.copy(REPO / "library" / "paper-coupling.png", c.with_suffix(".png"))  # drawn before PNGs were marked
    check_output(c, "coupling", also=(card_path(c), c.with_suffix(".png")))
    c2 = tmp_path / "new.safetensors"
    shutil.copy(REPO / "library" / "paper-coupling.png", c2.with_suffix(".png"))
    with pytest.raises(InputError, match="did not write"):
        check_output(c2, "coupling", also=(card_path(c2), c2.with_suffix(".png")))
    d = tmp_path / "d"
    shutil.copytree(REPO / "sensing" / "compare-demo", d)  # a legacy product folder
    check_output(d / "compare.png", "figure")
    with pytest.raises(InputError):
        check_output(tmp_path / "new.png", "figure")  # a PNG metadesign did not draw, in a user's folder
    run = tmp_path / "run"
    run.mkdir()
    with zipfile.ZipFile(run / "checkpoint.pt", "w") as zf:
        zf.writestr("checkpoint/data.pkl", b"\x80")
    assert identify(run) == "training-run"


def test_packaged_recipes_by_name(tmp_path, monkeypatch):
    """`metadesign run pipeline-demo` finds the packaged recipe (a checkout's or a wheel's); a path that
    exists wins over a name."""
    from metadesign.paths import recipe_path

    assert recipe_path("pipeline-demo", "sensing") == REPO / "sensing" / "pipeline-demo.toml"
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pipeline-demo").write_text("mine")
    assert recipe_path("pipeline-demo", "sensing") == Path("pipeline-demo")
    assert recipe_path("nothing-of-that-name", "sensing") == Path("nothing-of-that-name")


def test_nothing_is_written_into_the_package(tmp_path):
    """Outputs never land in the installed package (a wheel's products/ included): one line."""
    import metadesign
    from metadesign.outputs import check_output
    from metadesign.validation import InputError

    pkg = Path(metadesign.__file__).resolve().parent
    for out, kind in ((pkg / "products" / "library" / "fig.png", "figure"), (pkg / "demo-out", "demo")):
        with pytest.raises(InputError, match="inside the installed metadesign package"):
            check_output(out, kind)
    check_output(tmp_path / "fig.png", "figure")


# commands that keep a resume folder beside their output (OUT.partial)
SCRATCH_COMMANDS = ["library build", "library supercells", "dataset import"]


@pytest.mark.parametrize("content", ["empty", "with-file"])
@pytest.mark.parametrize("cmd", SCRATCH_COMMANDS)
def test_a_users_folder_where_the_resume_folder_goes_is_refused(cmd, content, inputs, tmp_path, capsys):
    """A folder a user made at ``OUT.partial`` (even an empty one) is never taken for a resume folder (and
    so never removed): one line, exit 2, nothing written or changed."""
    from metadesign.execution import scratch_path

    base = tmp_path / "in"
    shutil.copytree(inputs, base)
    ph = tmp_path / "work" / "out"
    ph.parent.mkdir()
    argv = _argv(cmd, base, ph)
    out = _out_of(argv, ph)
    user = scratch_path(out)
    user.mkdir()
    if content == "with-file":
        (user / "notes.txt").write_text("mine")
    before = {"in": _tree(base), "work": _tree(ph.parent)}
    rc, _, err = run_main(argv, capsys)
    assert rc == 2, (cmd, content, err[-3:])
    assert len(err) == 1 and err[0].startswith("metadesign: error:"), err
    assert f"{user}: exists and metadesign did not make it" in err[0] and "resume folder" in err[0], err
    assert {"in": _tree(base), "work": _tree(ph.parent)} == before
    assert user.is_dir() and (content == "empty" or (user / "notes.txt").read_text() == "mine")


MINI_RECIPE = """[stack]
wavelength_nm = 1550.0
period_um = 0.7
height_um = 1.2
[sweep]
w_min_um = 0.20
w_max_um = 0.26
step_nm = 10.0
[solver]
n_harmonics = 60
[convergence]
reference_n_harmonics = 80
check_cells_um = [[0.3, 0.2]]
tolerance_rad = 0.5
"""


def test_an_interrupted_job_resumes_from_the_folder_metadesign_made(tmp_path, capsys):
    """The resume folder carries the scratch marker from its first moment: a build stopped after a chunk
    (as a SIGKILL would) is resumed by the command, and the folder goes once the library is written."""
    from metadesign.execution import is_scratch, scratch_path
    from metadesign.library.build import build_library
    from metadesign.library.recipe import load_recipe
    from metadesign.outputs import check_output
    from metadesign.tasks import SCRATCH_MARK

    rec = tmp_path / "mini.toml"
    rec.write_text(MINI_RECIPE)
    out = tmp_path / "mini.npz"
    with pytest.raises(KeyboardInterrupt):
        build_library(load_recipe(rec), out, workers=1, chunk_size=5, _stop_after_chunks=1)
    part = scratch_path(out)
    assert is_scratch(part) and (part / SCRATCH_MARK).is_file() and len(list(part.glob("chunk-*.npz"))) == 1
    check_output(out, "unit-cell-library", scratch=(part,))  # ours: accepted
    rc, _, err = run_main(["library", "build", rec, "-o", out, "-j", "1"], capsys)
    assert rc == 0, err
    assert any("resuming: 1/" in line for line in err), err
    assert out.is_file() and not part.exists()


def test_a_task_folder_never_removes_a_folder_metadesign_did_not_make(tmp_path):
    from metadesign.library.supercells import remove_partial
    from metadesign.tasks import SCRATCH_MARK, TaskFolder, is_scratch
    from metadesign.validation import InputError

    key, other = "a" * 64, "b" * 64
    for content in ("empty", "with-file"):
        user = tmp_path / content
        user.mkdir()
        if content == "with-file":
            (user / "chunk-00000.npz").write_text("mine")
        before = _tree(user)
        with pytest.raises(InputError, match="metadesign did not make it"):
            TaskFolder(user, key)  # another job's key: it would discard the folder
        TaskFolder(user).remove()
        remove_partial(user)
        assert user.is_dir() and _tree(user) == before and not is_scratch(user)
    # a folder it made (the marker first, its parents too) is its to discard and remove
    f = TaskFolder(tmp_path / "out.partial" / "nG-5", key)
    assert is_scratch(tmp_path / "out.partial") and is_scratch(f.root)
    f.save("t", {"x": np.zeros(2)})
    g = TaskFolder(f.root, other)
    assert g.manifest()["key"] == other and not g.has("t")
    g.remove()
    assert not g.root.exists() and (tmp_path / "out.partial" / SCRATCH_MARK).is_file()
    remove_partial(tmp_path / "out.partial")
    assert not (tmp_path / "out.partial").exists()
