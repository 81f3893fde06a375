"""The ``metadesign`` command line: assembles the stage CLIs.

Each stage owns its sub-commands (``metadesign/<stage>/cli.py``).  Every
sub-command validates its inputs first; a bad input prints one line
``metadesign: error: ...`` and exits with status 2 without writing anything.
"""

from __future__ import annotations

import os

# Single-threaded BLAS/OpenMP unless the user asked otherwise: the machines
# this runs on are small and shared, and we parallelise with processes.
for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from . import __version__  # noqa: E402
from .cliutil import Parser, emit, log_to, out_dir  # noqa: E402
from .validation import ValidationError  # noqa: E402

__all__ = ["main", "build_parser"]


def _cmd_demo(a: argparse.Namespace) -> int:
    from .demo import run_demo

    summary = run_demo(out_dir(a.output), log=log_to(a.json))
    emit(summary, a.json, summary["text"])
    return 0 if summary["passed"] else 1


def _cmd_run(a: argparse.Namespace) -> int:
    from .pipeline import run_pipeline

    out = out_dir(a.output or Path(a.recipe).with_suffix("").with_name(Path(a.recipe).stem + "-out"))
    rep = run_pipeline(a.recipe, out, log=log_to(a.json))
    lines = [f"pipeline {a.recipe} -> {out}"]
    for k, v in rep["stages"].items():
        lines.append(f"  {k:<11} {'up to date' if v.get('skipped') else '%.1f s' % v['seconds']}")
    for row in rep["tables"].get("NPiB summary", []):
        lines.append(f"  NPiB (noise {row['noise']}): none {row['npib_none']:.3f}, U-Net {row['npib_unet']:.3f}, "
                     f"phase conjugate {row['npib_phase_conjugate']:.3f}; captured {row['captured_fraction']:.2f}")
    lines.append(f"  report     {rep['report']}")
    emit({"stages": rep["stages"], "tables": rep["tables"], "report": rep["report"]}, a.json, "\n".join(lines))
    return 0


def _stage_modules():
    from .design import cli as design_cli
    from .layouts import cli as layout_cli
    from .library import cli as library_cli
    from .sensing import cli as sensing_cli
    from .turbulence import cli as turbulence_cli

    mods = [library_cli, design_cli, layout_cli, sensing_cli, turbulence_cli]
    try:
        from .reconstruction import cli as reconstruction_cli

        mods.append(reconstruction_cli)
        from .baselines import cli as baselines_cli

        mods.append(baselines_cli)
    except ImportError:  # pragma: no cover - stage 6 not installed
        pass
    return mods


#: historical spellings: ``design RECIPE`` = ``design build RECIPE``, ``layout DESIGN`` = ``layout write DESIGN``
_DEFAULT_ACTIONS = {"design": ("build", ("build", "plot", "show")),
                    "layout": ("write", ("write", "verify", "preview"))}


def _legacy(argv: list[str]) -> list[str]:
    if len(argv) >= 2 and argv[0] in _DEFAULT_ACTIONS:
        default, actions = _DEFAULT_ACTIONS[argv[0]]
        if argv[1] not in actions and not argv[1].startswith("-"):
            return [argv[0], default, *argv[1:]]
    return argv


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="metadesign", description="Design, lay out and verify birefringent metasurfaces for "
               "single-shot phase-diversity wavefront sensing.")
    p.add_argument("--version", action="version", version=f"metadesign {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    demo = sub.add_parser("demo", help="run the embedded demo through every stage",
                          description="Run the small embedded demo through every stage (from the committed "
                          "unit-cell library) and write a summary and figures.")
    demo.add_argument("-o", "--output", default="demo-out", help="output folder (default: ./demo-out)")
    demo.add_argument("--json", action="store_true", help="print the summary as JSON")
    demo.set_defaults(func=_cmd_demo)
    run = sub.add_parser("run", help="every stage from a pipeline recipe, with an HTML report",
                         description="Run a pipeline recipe: library, design, layout (verified), as-fabricated "
                         "PSFs and fab study, turbulence validation, dataset, training (or a given model), "
                         "evaluation; stages whose inputs did not change are skipped; writes OUT/report.html "
                         "(self-contained: every figure and table).")
    run.add_argument("recipe", help="pipeline recipe (TOML), e.g. sensing/pipeline-demo.toml")
    run.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe)")
    run.add_argument("--json", action="store_true", help="print the summary as JSON")
    run.set_defaults(func=_cmd_run)
    for mod in _stage_modules():
        mod.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    a = parser.parse_args(_legacy(argv))
    try:
        return int(a.func(a) or 0)
    except ValidationError as exc:
        print(f"metadesign: error: {str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__}",
              file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and friends
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("metadesign: interrupted; finished work is kept, rerun the same command to resume",
              file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
