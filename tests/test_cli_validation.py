"""Every sub-command's numeric options against bad values, and the input and
output checks of the validation layer: exit 0 or 2, one line on stderr, no
traceback, nothing written on exit 2."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import pytest

from metadesign.cli import build_parser, main

REPO = Path(__file__).resolve().parents[1]
BAD = ["nan", "inf", "-inf", "-1", "0", "1e300"]


def _leaves(parser, prefix=()):
    """(command words, leaf parser) of every sub-command."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield prefix, parser
        return
    for name, p in subs[0].choices.items():
        yield from _leaves(p, prefix + (name,))


def _numeric_options(p):
    for a in p._actions:
        if a.option_strings and getattr(a.type, "metadesign_numeric", False) or (
                a.option_strings and a.type in (int, float)):
            yield a


def _copy(ds: Path | None, to: Path) -> Path | None:
    """A private copy of the shared tiny dataset for commands that write into a dataset."""
    if ds is None:
        return None
    if not to.exists():
        shutil.copytree(ds, to)
    return to


def _tiny_recipe(out: Path) -> Path:
    """A 0.1 mm design recipe (142 cells): the tiled build in a second."""
    rec = out / "tiny-design.toml"
    if not rec.exists():
        rec.write_text(f'[design]\nlibrary = "{REPO / "library" / "paper.npz"}"\nwavelength_nm = 1550.0\n'
                       'period_um = 0.7\naperture_mm = 0.1\n[discretizer]\ntile_rows = 32\n')
    return rec


def _base(cmd: tuple, prod: dict, out: Path, ds: Path | None = None) -> list[str] | None:
    d, lay, sen = str(prod["design"]), str(prod["layout"]), str(prod["sensor"])
    return {
        ("library", "build"): [str(REPO / "library" / "paper.toml"), "-o", str(out / "lib.npz")],
        ("library", "show"): [],
        ("library", "plot"): ["-o", str(out / "s1.png")],
        ("library", "export"): ["--csv", str(out / "lib.csv")],
        ("library", "lpa-check"): [lay, "--supercells", "1", "--harmonics", "50", "--check", "0", "-o", str(out / "lpa")],
        ("library", "supercells"): [str(REPO / "library" / "paper-supercells.toml"), "-o", str(out / "t.npz")],
        ("library", "coupling"): [str(out / "no-table.npz"), "-o", str(out / "c.safetensors")],
        ("library", "coupling-check"): [d, "--sensor", sen, "-o", str(out / "cc")],
        ("library", "coupling-sweep"): [str(out / "no-report"), "-o", str(out / "sweep.png")],
        ("library", "ladder"): [str(out / "no-table.npz"), "-o", str(out / "l.json")],
        ("library", "active"): [str(out / "no-recipe.toml"), "--reference", str(out / "no-table.npz")],
        ("library", "patches"): [str(out / "no-design"), "-o", str(out / "p.json")],
        ("library", "peds"): [str(out / "no-table.npz"), "-o", str(out / "peds.json")],
        ("design", "compensate"): [d, "-o", str(out / "dc")],
        ("design", "build"): [str(REPO / "layouts" / "demo.toml"), "-o", str(out / "d")],
        ("design", "show"): [d],
        ("design", "plot"): [d, "-o", str(out / "s2.png")],
        ("layout", "write"): [d, "-o", str(out / "lay")],
        ("layout", "verify"): [lay],
        ("layout", "tiled"): [str(_tiny_recipe(out)), "-o", str(out / "tl"), "--tile", "64", "-j", "1"],
        ("layout", "preview"): [lay, "-o", str(out / "prev.png")],
        ("psf",): [lay, "--sensor", sen, "-o", str(out / "psf")],
        ("fab-study",): [lay, "--sensor", sen, "--bias-nm", "0", "-o", str(out / "fs")],
        ("turbulence", "show"): [],
        ("turbulence", "validate"): ["--samples", "2", "--rytov", "0.3", "-o", str(out / "tv")],
        ("demo",): ["-o", str(out / "demo")],
        ("dataset", "build"): [str(REPO / "sensing" / "dataset-demo.toml"), "-o", str(out / "ds")],
        ("dataset", "show"): [str(ds)],
        ("dataset", "verify"): [str(ds)],
        ("dataset", "operators"): [str(_copy(ds, out / "ds-ops"))],
        ("dataset", "plot"): [str(ds), "-o", str(out / "ds.png")],
        ("dataset", "import"): [str(out / "no-captures"), "-o", str(out / "imp"), "--calibration",
                                str(out / "no-captures" / "flat.csv"), "--reference", str(ds)],
        ("dataset", "synth-captures"): [str(ds), "--device", str(ds), "--samples", "1", "-o", str(out / "cap")],
        ("train",): [str(REPO / "sensing" / "train-demo.toml"), "--dataset", str(ds), "-o", str(out / "run")],
        ("export",): [str(REPO / "sensing" / "models" / "demo-unet-long.safetensors"), "--onnx", str(out / "m.onnx")],
        ("table-s2",): [str(REPO / "sensing" / "table-s2.toml"), "-o", str(out / "t2")],
        ("run",): [str(REPO / "sensing" / "pipeline-demo.toml"), "-o", str(out / "pipe")],
        ("evaluate",): [str(REPO / "sensing" / "models" / "demo-unet-long.safetensors"), str(ds), "-o", str(out / "ev")],
        ("phasemap",): [lay, "-o", str(out / "pm")],
        ("tolerance",): [str(REPO / "sensing" / "tolerance-demo.toml"), "-o", str(out / "tol")],
        ("transfer",): [str(REPO / "sensing" / "transfer-demo.toml"), "-o", str(out / "tr")],
        ("compare",): ["NONE", str(ds), "-o", str(out / "cmp")],
        ("retrieve",): ["NONE", str(ds), "-o", str(out / "ret")],
        ("loop",): [str(out / "no-loop.toml"), "-o", str(out / "loop")],
        ("loop-map",): [str(out / "no-map.toml"), "-o", str(out / "map")],
        ("polcam",): [str(out / "no-polcam.toml"), "-o", str(out / "polcam")],
        ("codesign",): [str(out / "no-run"), "--dataset", str(ds), "--base", str(REPO / "layouts" / "demo.toml"),
                        "-o", str(out / "cd")],
    }.get(cmd)


def _snapshot(*dirs) -> set:
    return {(str(p), p.stat().st_size, p.stat().st_mtime_ns) for d in dirs for p in Path(d).rglob("*")}


def _cases():
    for cmd, p in _leaves(build_parser()):
        for act in _numeric_options(p):
            for v in BAD:
                yield pytest.param(cmd, act.option_strings[-1], act.nargs, v, id=f"{' '.join(cmd)} {act.option_strings[-1]} {v}")


def test_every_leaf_command_has_a_base_invocation(demo_products, tmp_path):
    missing = [" ".join(c) for c, _ in _leaves(build_parser()) if _base(c, demo_products, tmp_path) is None]
    assert not missing, f"add these sub-commands to _base(): {missing}"


_BASE_RUN: set = set()  # commands whose base invocation has run in this process


def _same_as_base(cmd: tuple, argv: list, base: list) -> bool:
    """True when ``argv`` parses to the same options as ``base`` and that command's base invocation has
    already run here (the first such case runs it: the same arguments, the same run)."""
    import contextlib
    import io

    p = build_parser()
    try:
        with contextlib.redirect_stderr(io.StringIO()):  # a value argparse refuses: the case runs as it is
            same = vars(p.parse_args([str(a) for a in argv])) == vars(p.parse_args([str(a) for a in base]))
    except SystemExit:
        return False
    if not same:
        return False
    if cmd in _BASE_RUN:
        return True
    _BASE_RUN.add(cmd)
    return False

@pytest.mark.parametrize("cmd,opt,nargs,value", list(_cases()))
def test_numeric_options_exit_0_or_2_with_one_line(cmd, opt, nargs, value, demo_products, tmp_path, capsys,
                                                    monkeypatch, tiny_dataset):
    monkeypatch.chdir(tmp_path)
    base = _base(cmd, demo_products, tmp_path, tiny_dataset)
    n = 3 if nargs == 3 else 1
    argv = [*cmd, *base, opt, *([value] * n)]
    if opt == "--bias-nm" and "--bias-nm" in base:  # replace the base value
        i = argv.index("--bias-nm")
        del argv[i:i + 2]
    if _same_as_base(cmd, argv, [*cmd, *base]):
        return  # the value parses to what the base invocation gives (the option's default): that run is done
    before = _snapshot(tmp_path, demo_products["design"], tiny_dataset)
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse errors
        rc = exc.code
    err = capsys.readouterr().err
    assert rc in (0, 2), (argv, rc, err)
    assert "Traceback" not in err
    if rc == 2:
        lines = [x for x in err.splitlines() if x.strip()]
        assert len(lines) == 1 and lines[0].startswith("metadesign: error:"), err
        assert _snapshot(tmp_path, demo_products["design"], tiny_dataset) == before, "files written on exit 2"


def _one_error(argv, capsys, match: str):
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("metadesign: error:"), (rc, err)
    assert match in lines[0], lines[0]
    return lines[0]


def test_wrong_kinds_of_file_are_one_line(demo_products, tmp_path, capsys):
    npy = tmp_path / "a.npy"
    np.save(npy, np.zeros(3))
    lay, sen = demo_products["layout"], demo_products["sensor"]
    _one_error(["library", "show", npy], capsys, "single .npy array")
    _one_error(["design", "show", npy], capsys, "single .npy array")
    _one_error(["psf", lay, "--sensor", sen, "--wavefront", npy, "-o", tmp_path / "p"], capsys, "single .npy")
    obj = tmp_path / "obj.npz"
    np.savez(obj, field=np.array([{"a": 1}], dtype=object))
    msg = _one_error(["psf", lay, "--sensor", sen, "--wavefront", obj, "-o", tmp_path / "p"], capsys, "never loaded")
    assert "allow_pickle" not in msg
    bad = tmp_path / "nan.npz"
    np.savez(bad, field=np.full((180, 180), np.nan, np.complex64))
    _one_error(["psf", lay, "--sensor", sen, "--wavefront", bad, "-o", tmp_path / "p"], capsys, "NaN")
    assert not (tmp_path / "p").exists()


def test_outputs_are_checked_before_work(demo_products, tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    lay, sen = demo_products["layout"], demo_products["sensor"]
    _one_error(["psf", lay, "--sensor", sen, "-o", f], capsys, "not a folder")
    _one_error(["library", "export", "--csv", tmp_path], capsys, "is a folder")
    _one_error(["psf", lay, "--sensor", sen, "-o", tmp_path / "no" / "such"], capsys, "does not exist")
    _one_error(["turbulence", "validate", "-o", f], capsys, "not a folder")
    _one_error(["layout", "preview", lay, "--window", 0, 0, 100000], capsys, "CELLS")
    _one_error(["library", "build", REPO / "library" / "paper.toml", "-j", 100000, "-o", tmp_path / "l.npz"],
               capsys, "--workers")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.parametrize("section,change,match", [
    ("convergence", "check_cells_um = []", "convergence.check_cells_um"),
    ("sweep", "w_min_um = 0.3\nw_max_um = 0.3", "sweep.w_min_um"),
])
def test_bad_library_recipes(section, change, match, tmp_path, capsys):
    text = (REPO / "library" / "paper.toml").read_text()
    text = text.replace(f"[{section}]", f"[{section}]\n{change}", 1)
    # drop the recipe's own value of each key we set
    keys = [ln.split("=")[0].strip() for ln in change.splitlines()]
    lines, seen = [], set()
    for ln in text.splitlines():
        k = ln.split("=")[0].strip()
        if k in keys and k in seen:
            continue
        seen.add(k)
        lines.append(ln)
    r = tmp_path / "r.toml"
    r.write_text("\n".join(lines))
    _one_error(["library", "build", r, "-o", tmp_path / "x.npz"], capsys, match)
    assert not (tmp_path / "x.npz").exists()


def _design_recipe(tmp_path, **design):
    text = (REPO / "layouts" / "demo.toml").read_text().replace('"../library/paper.npz"',
                                                               f'"{REPO / "library" / "paper.npz"}"')
    for k, v in design.items():
        import re

        if re.search(rf"^{k} = ", text, flags=re.M):
            text = re.sub(rf"^{k} = .*$", f"{k} = {v}", text, flags=re.M)
        else:
            text = text.replace("[design]\n", f"[design]\n{k} = {v}\n", 1)
    p = tmp_path / "r.toml"
    p.write_text(text)
    return p


def test_bad_design_recipes_refused_at_the_start(tmp_path, capsys):
    _one_error(["design", _design_recipe(tmp_path, supercell=1), "-o", tmp_path / "o"], capsys, "design.supercell")
    big = _design_recipe(tmp_path, aperture_mm=300.0)
    _one_error(["design", big, "-o", tmp_path / "o"], capsys, "GiB of memory")
    _one_error(["design", _design_recipe(tmp_path, clear_aperture='"polygon"'), "-o", tmp_path / "o"], capsys,
               "needs exactly one")
    assert not (tmp_path / "o").exists()


def test_bad_sensing_and_turbulence_recipes(tmp_path, capsys, demo_products):
    from metadesign.sensing.model import sensing_from_dict
    from metadesign.turbulence.scenario import scenario_from_dict
    from metadesign.validation import ValidationError

    with pytest.raises(ValidationError, match="noise.photons_at_peak"):
        sensing_from_dict({"noise": {"photons_at_peak": 1e20}})
    with pytest.raises(ValidationError, match="noise.read_noise_e"):
        sensing_from_dict({"noise": {"read_noise_e": 3.0}})
    big = tmp_path / "t.toml"
    big.write_text("[path]\nn_screens = 200\n[grid]\nn = 8192\nspacing_mm = 0.1\n")
    sc = scenario_from_dict({"path": {"n_screens": 200}, "grid": {"n": 8192, "spacing_mm": 0.1}})
    assert sc.sample_bytes > 50e9
    try:
        rc = main(["turbulence", "show", str(big)])
    except SystemExit as exc:
        rc = exc.code
    out = capsys.readouterr().out
    assert rc == 2 and "memory per sample" in out and "INFEASIBLE" in out


def test_spec_dataclasses_validate_themselves():
    from metadesign.sensing.sensor import NoiseSpec, SensorSpec
    from metadesign.sensing.transmission import Perturbation
    from metadesign.turbulence.path import Scenario
    from metadesign.validation import ValidationError

    for bad in (dict(bias_x=float("nan")), dict(jitter=float("inf")), dict(jitter=-1e-9), dict(seed=-1),
                dict(corner_radius=float("nan"))):
        with pytest.raises(ValidationError):
            Perturbation(**bad)
    for bad in (dict(gaussian_sigma=float("nan")), dict(photons_at_peak=1e20), dict(read_noise_e=2.0),
                dict(bit_depth=0), dict(seed=-1)):
        with pytest.raises(ValidationError):
            NoiseSpec(**bad)
    for bad in (dict(width_px=642), dict(distance=float("inf")), dict(pixel_pitch=0.0)):
        with pytest.raises(ValidationError):
            SensorSpec(**bad)
    for bad in (dict(rytov=0.0), dict(rytov=float("nan")), dict(n_grid=16), dict(dx=-1.0)):
        with pytest.raises(ValidationError):
            Scenario(**bad)
    assert issubclass(ValidationError, ValueError)


def test_json_summaries_are_strict_json(demo_products, tmp_path, capsys):
    import json

    rc = main(["psf", str(demo_products["layout"]), "--sensor", str(demo_products["sensor"]), "-o",
               str(tmp_path / "p"), "--json"])
    out = capsys.readouterr().out
    assert rc == 0
    json.loads(out, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))


@pytest.mark.parametrize("argv,dest,value", [
    (["evaluate", "M", "D", "--noise", "5"], "noise", [5.0]),
    (["evaluate", "M", "D", "--noise-percent", "5"], "noise", [5.0]),
    (["compare", "M", "D", "--noise", "2"], "noise", 2.0),
    (["compare", "M", "D", "--noise-percent", "2"], "noise", 2.0),
    (["dataset", "operators", "D", "--splits", "train", "val"], "splits", ["train", "val"]),
    (["dataset", "operators", "D", "--split", "train", "val"], "splits", ["train", "val"]),
    (["export", "M", "--onnx", "m.onnx"], "onnx", "m.onnx"),
    (["export", "M", "-o", "m.onnx"], "onnx", "m.onnx"),
    (["library", "export", "--csv", "l.csv"], "csv", "l.csv"),
    (["library", "export", "--output", "l.csv"], "csv", "l.csv"),
    (["dataset", "synth-captures", "P", "--device", "D", "-o", "C", "--limit", "3"], "samples", 3),
    (["library", "lpa-check", "L", "--limit", "7", "--noise-percent", "2"], "samples", 7),
    (["dataset", "plot", "D", "--limit", "2"], "samples", 2),
    (["dataset", "build", "R", "--samples", "20"], "samples", 20),
])
def test_one_option_convention_with_the_old_spellings_as_aliases(argv, dest, value):
    """Units in option names (--noise-percent), --limit for 'at most N samples', --split, -o/--output for
    every output; the old spellings still parse to the same thing."""
    a = build_parser().parse_args(argv)
    assert getattr(a, dest) == value


@pytest.mark.parametrize("argv", [["dataset", "synth-captures", "P", "--device", "D", "-o", "C", "--samples", "3"],
                                  ["library", "lpa-check", "L", "--samples", "7"],
                                  ["library", "coupling-check", "D", "--samples", "7"],
                                  ["dataset", "plot", "D", "--samples", "2"]])
def test_samples_has_one_meaning(argv, capsys):
    """#32: --samples is how many samples to make (dataset build, turbulence validate); where a command
    takes at most N samples of a split, --samples is one line naming --limit."""
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--limit N" in err[0]
