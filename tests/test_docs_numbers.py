"""Numbers have one source (#52): the measured results the documentation quotes are the committed JSON
records'.  The results page is built from them (``docs/_ext/measured.py``: MyST substitutions, read when
the pages are built); the README and the guides, which GitHub shows as they are, quote some of the same
numbers, and each quote below is checked against its record (so "10 cm written in 37 min" cannot stand
beside the record's 10.4 min again)."""

from __future__ import annotations

import importlib
import json
import math
import re
import subprocess
import sys

import pytest
from conftest import REPO

sys.path.insert(0, str(REPO / "docs" / "_ext"))
M = importlib.import_module("measured")  # docs/_ext/measured.py: the records the pages quote

#: per page, the phrases that quote a record ({name}: MEASURED[name], formatted); whitespace is free
QUOTES = {
    "README.md": [
        ("`layouts/wide-100mm.toml`: {wide_pillars_1e10}e10 pillars written in {wide_build_min} min, every one "
         "verified in {wide_verify_min} min under 2 GB"),
        "| LPA (unit-cell library) | {lpa_mean2} / {lpa_p90_2} |",
        "| coupling model (`find_coupling`, pair network) | {coupling_mean} / {coupling_p90} |",
        "**{peds_mean} / {peds_p90}** (certified; goal 0.05 / 0.10)",
        ("spots lose {cc_loss_pct} +- 0.8 % of their power and {cc_strehl_drop} +- 0.002 of Strehl to the "
         "coupling, and its foci move {cc_focal} +- {cc_focal_se} um"),
        "({cc_coupled_loss_pct} %, {cc_coupled_strehl_drop}, {cc_coupled_focal} um) hold",
        ("an under-etch by 30 nm gains {etch_under_gain_pct} % of focused power and an over-etch loses "
         "{etch_over_loss_pct} %"),
        "is {cc_npib} +- {cc_npib_se} against {cc_lpa_npib} through the LPA device",
        "ring adds {ring_beyond_mean} / {ring_beyond_p90} that no 2 x 2 model sees",
        ("gives back {reopt_gain_pct} % of focused power ({reopt_eff} +- {reopt_eff_se} against {reopt_start_eff} "
         "+- {reopt_start_eff_se})"),
        ("captured fraction {rt_realtime_commands_cf} at 5 % noise in {rt_realtime_commands_us} us per frame on one "
         "core (ONNX Runtime; {rt_speedup}x faster than the U-Net measured in the same run), "
         "{rt_realtime_commands_e2e} us from the camera's two frames"),
        ("At Rytov 0.5, f_G 100 Hz and 2 kHz the real-time metasurface loop keeps mean NPiB {mapw_rt_npib}, "
         "{mapw_vs_ideal} of the ideal-phase loop's (goal 0.8: met) and {mapw_vs_sh}x the Shack-Hartmann loop's"),
        "(`loop-map`: the first-stage network, one gain, 0.4, leak 0.99) gave {map_vs_ideal}.",
        ("metasurface loop keeps {loopw_rt_vs_ideal} of the ideal-phase loop's mean NPiB and {loopw_rt_vs_sh}x the "
         "Shack-Hartmann loop's; neither latency ({loopz_rt_vs_ideal} at zero latency)"),
        ("the in-focus channel's far-field peak instead (0.99 of the best overlap, the network 0.95) gives "
         "{loopp_rt_vs_ideal} too"),
        ("**At leak 0.95 (`sensing/loop-demo-w48-leak.toml`) the metasurface loop keeps {loopk_rt_vs_ideal} of the "
         "ideal-phase loop's mean NPiB and {loopk_rt_vs_sh}x the Shack-Hartmann loop's: both goals are met**"),
    ],
    "docs/guide/layout.md": [
        "**20,407,836,736 pillars in {wide_numpy_min} min at {wide_numpy_gb} GB peak**",
        "**{wide_build_min} min at {wide_build_gb} GB**",
        "in {wide_verify_min} min at {wide_verify_gb2} GB peak**",
        "one worker, {wide_psf_min} min at {wide_psf_gb} GB**",
    ],
    "docs/guide/library.md": [
        ("the focused power drops by {cc_loss_pct} +- 0.8 % from the LPA's (coupling model: {cc_coupled_loss_pct} %), "
         "the Strehl by {cc_strehl_drop} +- 0.002 ({cc_coupled_strehl_drop})"),
        "| **design, certified (PEDS, sampled)** | **{cc_eff} +- {cc_eff_se}** | **{cc_strehl} +- {cc_strehl_se}** |",
        "on 32 patches the ring is **{ring_beyond_mean} mean, {ring_beyond_p90} p90**",
        "| **PEDS** | 1,000 | **0.038 / 0.069** | **0.040 / 0.073** | **{peds_mean} / {peds_p90}** |",
    ],
    "docs/guide/fab-to-lab.md": [
        "| robust demo model, unadapted | {tr_unadapted} |",
        "| fine-tuned from the robust demo model (`--init`, 6 PiB epochs, ~2 min) | **{tr_finetuned}** |",
    ],
    "docs/guide/baselines.md": [
        "| U-Net (robust) | {cmp_unet} |",
        "| Shack-Hartmann (5 x 5, zonal) | {cmp_shack_hartmann} |",
    ],
}


def _flat(text: str) -> str:
    return re.sub(r"\s+", " ", text)


def _quoted(page_text: str, template: str, values: dict) -> bool:
    return _flat(template.format(**values)).lower() in _flat(page_text).lower()


@pytest.fixture(scope="module")
def values():
    return M.measured()


def test_every_quoted_number_reads_from_a_committed_record(values):
    out = subprocess.run(["git", "-C", str(REPO), "ls-files", "*.json"], check=False, capture_output=True, text=True)
    committed = set(out.stdout.split()) if out.returncode == 0 else None
    for name, q in M.MEASURED.items():
        assert math.isfinite(q.value()), name
        if isinstance(q, M.Q) and committed is not None:
            assert q.file in committed, f"{name}: {q.file} is not committed"
    assert len(values) == len(M.MEASURED) >= 150


@pytest.mark.parametrize("page", sorted(QUOTES))
def test_the_pages_quote_their_records(page, values):
    text = (REPO / page).read_text()
    wrong = [t.format(**values) for t in QUOTES[page] if not _quoted(text, t, values)]
    assert not wrong, f"{page} does not say (from the committed records): {wrong}"


def test_the_results_page_is_built_from_the_records_and_gives_numbers_not_paths():
    text = (REPO / "docs" / "results.md").read_text()
    used = re.findall(r"\{\{\s*(\w+)\s*\}\}", text)
    assert len(set(used)) >= 100 and set(used) <= set(M.MEASURED), sorted(set(used) - set(M.MEASURED))
    rows = [ln for ln in text.splitlines() if ln.startswith("|") and not ln.startswith("|---")]
    assert not [r for r in rows if re.search(r"\.json\b", r)], "a JSON path where a number belongs"
    reproduce = [re.split(r"(?<!\\)\|", r)[3] for r in rows if not r.startswith("| what")]
    assert reproduce and all("{reproduce}`" in c for c in reproduce), "a reproduce command without its link"
    # every other page quotes only names the records hold
    for page in (REPO / "docs").rglob("*.md"):
        if "_build" not in page.parts:
            assert set(re.findall(r"\{\{\s*(\w+)\s*\}\}", page.read_text())) <= set(M.MEASURED), page


def test_the_reproduce_links_find_their_commands():
    """Each ``{reproduce}`` command of the results page resolves: ``metadesign ...`` to a command of the CLI
    (its reference section), ``python benchmarks/X.py`` to a script that exists."""
    from metadesign.cli import build_parser

    sys.path.insert(0, str(REPO / "docs" / "_ext"))
    from cli_reference import _walk

    known = {name for name, _ in _walk(build_parser(), "metadesign")}
    cmds = re.findall(r"\{reproduce\}`([^`]+)`", (REPO / "docs" / "results.md").read_text())
    assert len(cmds) >= 20
    for cmd in cmds:
        target = M.command_target(cmd, known)
        assert target is not None, cmd
        if target[0] == "doc":
            assert (REPO / cmd.split()[1]).is_file(), cmd
    assert M.command_target("metadesign library coupling-check layouts/paper-5mm", known) == (
        "ref", "metadesign library coupling-check")
    assert M.command_target("metadesign no-such-command", known) == ("ref", "metadesign")


def test_a_stale_quote_fails_and_a_record_change_shows(tmp_path, values):
    """The check can fail: the README's old "37 min" against the record's build time; and a changed record
    changes the number the pages are built with (paths with list selectors and keys holding dots)."""
    stale = "`layouts/wide-100mm.toml`: 2.0e10 pillars written in 37 min, every one verified in 17 min under 2 GB"
    assert not _quoted(stale, QUOTES["README.md"][0], values)
    rec = {"rows": [{"case": "a", "x": {"0.5-0.6": 1.0}}, {"case": "b", "x": {"0.5-0.6": 120.0}}]}
    (tmp_path / "r.json").write_text(json.dumps(rec))
    q = M.Q("r.json", "rows[case=b]/x/0.5-0.6", "{:.1f}", 1 / 60)
    assert q.fmt.format(q.value(tmp_path)) == "2.0"
    assert M.lookup(rec, "rows[0]/x/0.5-0.6") == 1.0
    with pytest.raises(KeyError, match="no 'y'"):
        M.lookup(rec, "rows[0]/y")
    M._record.cache_clear()
    rec["rows"][1]["x"]["0.5-0.6"] = 60.0
    (tmp_path / "r.json").write_text(json.dumps(rec))
    assert q.fmt.format(q.value(tmp_path)) == "1.0"
