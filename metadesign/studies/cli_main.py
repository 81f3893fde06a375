"""``demo`` and ``run``: the commands a new user starts with (a pipeline recipe through every stage)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..cliutil import emit, out_dir
from ..io import atomic_write_text
from ..outputs import product
from ..paths import recipe_path, repo_root

__all__ = ["register", "DEMO_RECIPE"]


#: the recipe ``metadesign demo`` runs (packaged: sensing/demo-run.toml)
DEMO_RECIPE = "demo-run"


def _cmd_demo(a: argparse.Namespace) -> int:
    """``run`` on the packaged demo recipe, into ``./demo-out`` (a folder of kind "demo")."""
    return _run(recipe_path(DEMO_RECIPE, "sensing"), out_dir(a.output), "demo", a.json)


def _cmd_run(a: argparse.Namespace) -> int:
    recipe = recipe_path(a.recipe, "sensing")  # a path, or a packaged recipe's name: `run pipeline-demo`
    # the default output: beside a recipe of the user's, in the working directory for a packaged one
    packaged = recipe.resolve().is_relative_to(repo_root().resolve()) and not recipe.resolve().is_relative_to(
        Path.cwd().resolve())
    out = out_dir(a.output or (Path.cwd() if packaged else recipe.parent) / f"{recipe.stem}-out")
    return _run(recipe, out, "pipeline", a.json)


def _run(recipe: Path, out: Path, kind: str, as_json: bool) -> int:
    """A pipeline recipe into ``out``: each stage's line as it completes, then the headline, the checks and
    the report (``--json``: the summary alone, also written to OUT/summary.json); exit 1 on a failed check."""
    import time

    from .pipeline import run_pipeline

    def say(s):
        if not as_json:
            print(s, flush=True)

    t0 = time.perf_counter()
    with product(out, kind, {"recipe": recipe}):
        say(f"metadesign {'demo' if kind == 'demo' else 'run ' + str(recipe)} -> {out}/")
        rep = run_pipeline(recipe, out, log=say)
        failed = [c for c in rep["checks"] if not c["passed"]]
        summary = {"output": str(out), "recipe": str(recipe), "stages": rep["stages"], "tables": rep["tables"],
                   "checks": rep["checks"], "passed": not failed, "report": rep["report"],
                   "provenance": rep.get("provenance"), "seconds": time.perf_counter() - t0}
        atomic_write_text(out / "summary.json", json.dumps(summary, indent=2, sort_keys=True, default=str))
    lines = []
    est = (rep.get("headline") or {}).get("estimator", "U-Net")
    for row in rep["tables"].get("NPiB summary", []):
        lines.append(f"  NPiB at {row['noise_percent']:g} % noise: none {row['npib_none']:.3f}, {est} "
                     f"{row['npib_unet']:.3f}, phase conjugate {row['npib_phase_conjugate']:.3f}; captured "
                     f"{row['captured_fraction']:.2f}"
                     + (f" (U-Net alone {row['captured_fraction_unet_alone']:.2f})"
                        if "captured_fraction_unet_alone" in row else ""))
    figs = [Path(f).name for st in rep["stages"].values() for f in st.get("figures", [])]
    lines.append(f"  figures       {', '.join(figs)}")
    lines.append(f"  time          {summary['seconds']:.1f} s")
    lines.append(f"  checks        {len(rep['checks']) - len(failed)}/{len(rep['checks'])} passed"
                 + "".join(f"\n    FAILED: {c['check']}: {c['value']} (needs {c['threshold']})" for c in failed))
    lines.append(f"  report        {rep['report']}")
    emit(summary, as_json, "\n".join(lines))
    return 1 if failed else 0  # a failed check is a failed run


def register(sub, groups: dict | None = None) -> None:
    """``demo`` and ``run``: the commands a new user starts with."""
    demo = sub.add_parser("demo", help="run the embedded demo through every stage",
                          description="Run the small embedded demo through every stage (from the committed "
                          "unit-cell library): `run` on the packaged recipe demo-run (sensing/demo-run.toml); "
                          "writes summary.json, the figures and report.html; a second run is up to date.")
    demo.add_argument("-o", "--output", default="demo-out", help="output folder (default: ./demo-out)")
    demo.add_argument("--json", action="store_true", help="print the summary as JSON")
    demo.set_defaults(func=_cmd_demo)
    run = sub.add_parser("run", help="every stage from a pipeline recipe, with an HTML report",
                         description="Run a pipeline recipe: library, design, layout (verified), as-fabricated "
                         "PSFs and fab study, turbulence validation, dataset, training (or a given model), "
                         "evaluation (or fresh beacons through a second device: [beacons]); stages whose inputs "
                         "did not change are skipped; writes OUT/summary.json and OUT/report.html "
                         "(self-contained: every figure and table).")
    run.add_argument("recipe", help="pipeline recipe (TOML), e.g. sensing/pipeline-demo.toml, or the name of a "
                     "packaged one (pipeline-demo: works from a wheel install)")
    run.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe; for a packaged "
                     "recipe, in the working directory)")
    run.add_argument("--json", action="store_true", help="print the summary as JSON")
    run.set_defaults(func=_cmd_run)
