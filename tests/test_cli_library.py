"""CLI edge: bad recipes fail in one line with status 2 and write nothing."""

import json

import pytest
from conftest import run_cli

GOOD = """
[stack]
wavelength_nm = 1550.0
period_um = 0.7
height_um = 1.2
[sweep]
w_min_um = 0.2
w_max_um = 0.21
step_nm = 10.0
[solver]
n_harmonics = 40
[convergence]
reference_n_harmonics = 60
check_cells_um = [[0.3, 0.2]]
tolerance_rad = 1.0
"""

BAD = [
    ("[stack]\nwavelength_nm = 1550.0\nperiod_um = 0.7\nheight_um = 1.2\ncolour = 3\n", "stack.colour"),
    ("[stack]\nperiod_um = 0.7\nheight_um = 1.2\n", "stack.wavelength_nm"),
    (GOOD.replace("period_um = 0.7", "period_um = -0.7"), "stack.period_um"),
    (GOOD.replace("height_um = 1.2", 'height_um = "tall"'), "stack.height_um"),
    (GOOD.replace("w_max_um = 0.21", "w_max_um = 0.8"), "sweep.w_max_um"),
    (GOOD.replace("step_nm = 10.0", "step_nm = 25.0"), "sweep.step_nm"),
    (GOOD.replace("n_harmonics = 40", "n_harmonics = 4.5"), "solver.n_harmonics"),
    (GOOD + "[extra]\nx = 1\n", "extra"),
    ("this is = = not toml", "not valid TOML"),
]


@pytest.mark.parametrize("text,field", BAD)
def test_bad_recipe_one_line_exit_2_nothing_written(tmp_path, text, field):
    rec = tmp_path / "r.toml"
    rec.write_text(text)
    out = tmp_path / "out.npz"
    p = run_cli("library", "build", rec, "-o", out, "-j", "1")
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0] and "Traceback" not in p.stderr
    assert sorted(x.name for x in tmp_path.iterdir()) == ["r.toml"]


def test_build_show_export_roundtrip(tmp_path):
    rec = tmp_path / "r.toml"
    rec.write_text(GOOD)
    p = run_cli("library", "build", rec, "-j", "1", "--json")
    assert p.returncode == 0, p.stderr
    rep = json.loads(p.stdout)
    assert rep["cells"] == 4 and rep["convergence"]["passed"]
    lib = tmp_path / "r.npz"
    p = run_cli("library", "show", lib, "--json")
    s = json.loads(p.stdout)
    assert s["grid"]["n_wx"] == 2 and s["solver"]["n_harmonics"] < 40
    p = run_cli("library", "export", lib, "--csv", tmp_path / "t.csv")
    assert p.returncode == 0 and (tmp_path / "t.csv").read_text().count("\n") == 5


def test_unconverged_setting_is_refused(tmp_path):
    rec = tmp_path / "r.toml"
    rec.write_text(GOOD.replace("tolerance_rad = 1.0", "tolerance_rad = 0.0001"))
    p = run_cli("library", "build", rec, "-j", "1")
    assert p.returncode == 2 and "convergence check failed" in p.stderr
    assert not (tmp_path / "r.npz").exists()


def test_corrupt_library_one_line(tmp_path):
    f = tmp_path / "x.npz"
    f.write_bytes(b"PK\x03\x04garbage")
    p = run_cli("library", "show", f)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1


def test_killed_build_resumes_from_disk(tmp_path):
    """SIGKILL a real build after its first chunk lands; the rerun reuses it and gives the same bytes."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from conftest import REPO

    text = GOOD.replace("w_max_um = 0.21", "w_max_um = 0.28").replace("n_harmonics = 40", "n_harmonics = 160") \
        .replace("reference_n_harmonics = 60", "reference_n_harmonics = 200")
    rec = tmp_path / "r.toml"
    rec.write_text(text)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "metadesign", "library", "build", rec, "-j", "1"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    part = tmp_path / "r.npz.partial"
    t0 = time.time()
    while not list(part.glob("chunk-*.npz")) and time.time() - t0 < 120:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = len(list(part.glob("chunk-*.npz")))
    assert done >= 1 and not (tmp_path / "r.npz").exists()
    p = run_cli("library", "build", rec, "-j", "1")
    assert p.returncode == 0, p.stderr
    assert f"resuming: {done}/" in p.stderr
    clean = tmp_path / "clean.npz"
    assert run_cli("library", "build", rec, "-j", "2", "-o", clean).returncode == 0
    assert clean.read_bytes() == (tmp_path / "r.npz").read_bytes()
