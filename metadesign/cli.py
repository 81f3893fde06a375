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

from . import __version__  # noqa: E402
from .cliutil import Parser  # noqa: E402
from .validation import ValidationError  # noqa: E402

__all__ = ["main", "build_parser", "OPTIONAL"]

#: what the `learn` extra adds (pyproject.toml): a command that needs one of them on a core install is one line
OPTIONAL = {"torch", "zarr", "dask", "distributed", "safetensors", "onnx", "onnxruntime", "astropy"}


def _stage_modules():
    """The stage CLIs in pipeline order (each owns its commands)."""
    from .design import cli as design_cli
    from .layouts import cli as layout_cli
    from .library import cli as library_cli
    from .reconstruction import cli as reconstruction_cli
    from .sensing import cli as sensing_cli
    from .turbulence import cli as turbulence_cli

    return [library_cli, design_cli, layout_cli, sensing_cli, turbulence_cli, reconstruction_cli]


#: historical spellings: ``design RECIPE`` = ``design build RECIPE``, ``layout DESIGN`` = ``layout write DESIGN``
_DEFAULT_ACTIONS = {"design": ("build", ("build", "plot", "show", "compensate")),
                    "layout": ("write", ("write", "verify", "preview", "tiled"))}


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
    from .studies.cli import STUDY_MODULES
    from .studies.cli_main import register as register_main

    register_main(sub)  # demo and run first in the help
    groups: dict = {}
    for mod in _stage_modules():
        groups.update(mod.register(sub) or {})
    for mod in STUDY_MODULES:  # studies that combine stages: top-level commands and the stage groups' actions
        mod.register(sub, groups)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    a = parser.parse_args(_legacy(argv))
    from .io import enforce_claims

    enforce_claims(True)  # every write goes through the product layer (metadesign.outputs)
    try:
        if getattr(a, "scheduler", None):  # a refused scheduler is refused before any output is opened
            from .parallel import check_scheduler

            check_scheduler(a.scheduler)
        return int(a.func(a) or 0)
    except ValidationError as exc:
        print(f"metadesign: error: {str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__}",
              file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] not in OPTIONAL:
            raise
        print(f"metadesign: error: {a.command}: needs {exc.name}, which the core install leaves out: "
              f"pip install 'metadesign[learn]' (torch, zarr, dask, safetensors, onnx, onnxruntime, astropy)",
              file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and friends
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("metadesign: interrupted; finished work is kept, rerun the same command to resume",
              file=sys.stderr)
        return 130
    finally:
        enforce_claims(False)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
