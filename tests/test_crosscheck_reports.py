"""The cross-check scripts' report folder (``benchmarks/_paper_design.py``): opened through the product layer
before any work, its solves in ``OUT.partial`` (kept after a failure, removed once the report is written).
The scripts themselves need the paper design folder, which CI does not have: this checks the shared helper."""

import argparse
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import _paper_design as pd  # noqa: E402
from metadesign.execution import is_scratch, make_scratch, scratch_path  # noqa: E402
from metadesign.outputs import identify  # noqa: E402
from metadesign.validation import InputError  # noqa: E402


@pytest.fixture
def design(tmp_path):
    d = tmp_path / "design"
    d.mkdir()
    (d / "design.npz").write_bytes(b"not read here")
    return d


def test_report_written_and_scratch_removed(tmp_path, design):
    out = tmp_path / "report"
    with pd.report_output(out, {"design": design}) as (folder, scratch):
        assert folder == out and out.is_dir() and identify(out) == "crosscheck"
        assert scratch == scratch_path(out)
        make_scratch(scratch / "converged-0")  # what a solver makes: the resume folder, marked, and its step
        assert is_scratch(scratch)
        path = pd.write_report(folder, "crosscheck_x.py", {"per": 4}, {"rows": [1.5]})
    assert path == out / pd.REPORT
    assert json.loads(path.read_text()) == {"script": "crosscheck_x.py", "arguments": {"per": 4},
                                            "report": {"rows": [1.5]}}
    assert not scratch_path(out).exists()
    assert identify(out) == "crosscheck"
    with pd.report_output(out, {"design": design}) as (folder, _):  # its own report folder is replaced
        pd.write_report(folder, "crosscheck_x.py", {}, {})


def test_interrupted_run_keeps_its_solves_and_resumes(tmp_path, design):
    out = tmp_path / "report"
    with pytest.raises(KeyboardInterrupt), pd.report_output(out, {"design": design}) as (_, scratch):
        make_scratch(scratch / "converged-0")
        (scratch / "converged-0" / "chunk.npz").write_bytes(b"done")
        raise KeyboardInterrupt
    assert (scratch_path(out) / "converged-0" / "chunk.npz").exists()
    with pd.report_output(out, {"design": design}) as (folder, scratch):
        assert (scratch / "converged-0" / "chunk.npz").exists()  # a rerun finds the finished solves
        pd.write_report(folder, "crosscheck_x.py", {}, {})
    assert not scratch_path(out).exists() and (out / pd.REPORT).exists()


def test_refusals_write_nothing(tmp_path, design):
    users = tmp_path / "mine.txt"
    users.write_text("a user's file")
    with pytest.raises(InputError, match="not a folder"), pd.report_output(users, {"design": design}):
        pytest.fail("the block ran")
    assert users.read_text() == "a user's file" and not scratch_path(users).exists()

    out = tmp_path / "report"
    scratch_path(out).mkdir()  # a user's folder where the resume folder goes (even empty)
    with pytest.raises(InputError, match="did not make it"), pd.report_output(out, {"design": design}):
        pytest.fail("the block ran")
    assert not out.exists() and list(scratch_path(out).iterdir()) == []

    inside = design / "report"
    with pytest.raises(InputError, match="overlaps the input design"), pd.report_output(inside, {"design": design}):
        pytest.fail("the block ran")
    assert sorted(p.name for p in design.iterdir()) == ["design.npz"]


def test_without_output_a_temporary_folder(tmp_path):
    with pd.report_output(None) as (folder, scratch):
        assert folder is None and scratch.is_dir()
        (scratch / "x").write_text("solve")
        assert pd.write_report(folder, "crosscheck_x.py", {}, {}) is None
    assert not scratch.exists()
    keep = tmp_path / "solves"
    with pd.report_output(None, keep=keep) as (_, scratch):
        assert scratch == keep
        make_scratch(keep)
    assert keep.is_dir()  # --partial: the user's, kept


def test_crosscheck_refusal_is_one_line_exit_2(tmp_path, design, capsys):
    users = tmp_path / "mine"
    users.write_text("x")
    a = argparse.Namespace(output=str(users), json=True)
    assert pd.crosscheck(a, "crosscheck_x.py", {"design": design}, lambda s: pytest.fail("work done"), print) == 2
    err = capsys.readouterr().err
    assert err.startswith("crosscheck_x.py: error: ") and err.count("\n") == 1
    out = tmp_path / "report"
    a = argparse.Namespace(output=str(out), json=True)
    assert pd.crosscheck(a, "crosscheck_x.py", {"design": design}, lambda s: {"n": 1}, print) == 0
    assert json.loads(capsys.readouterr().out) == {"n": 1}
    assert json.loads((out / pd.REPORT).read_text())["arguments"] == {"output": str(out), "json": True}
