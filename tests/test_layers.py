"""The package's layering, enforced: a stage imports only what lies below it in the pipeline, never a
later stage and never another package's private name; studies sit on top; internal imports sit at
module top (the CLI modules, ``cli.py`` and ``cli_*.py``, which defer their stage's implementation so that ``--help`` and stage-1
commands do not load torch, excepted)."""

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "metadesign"

#: the shared edges: used by everything, import only each other
EDGES = {"conventions", "config", "io", "validation", "outputs", "tasks", "execution", "scratch", "cards", "cliutil", "parallel", "paths",
         "plotting", "timing", "lazy",
         "determinism", "deflate", "jit"}
#: subpackages in pipeline order (a module may import its own level and those below)
ORDER = ["optics", "library", "design", "layouts", "sensing", "turbulence", "reconstruction", "studies"]
TOP = {"cli", "__main__"}  # the assembler


def level(module: str) -> int:
    """0 for the edges (and the package root), 1.. for the stages in order, then studies, then the CLI."""
    parts = module.split(".")
    if len(parts) == 1:
        return 0
    head = parts[1]
    if head in EDGES:
        return 0
    if head in ORDER:
        return 1 + ORDER.index(head)
    if head in TOP:
        return len(ORDER) + 1
    raise AssertionError(f"{module}: not placed in the layering (add it to EDGES, ORDER or TOP)")


def package_of(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else parts[0]


def module_name(path: Path) -> tuple[str, bool]:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        return ".".join(parts[:-1]), True
    return ".".join(parts), False


def internal_imports(source: str, module: str, is_pkg: bool):
    """(line, target module, imported names, at module top?) of every metadesign import in ``source``."""
    tree = ast.parse(source)
    top = set(map(id, tree.body))
    for node in tree.body:  # ``if TYPE_CHECKING:`` imports are the module's own (annotations only)
        if isinstance(node, ast.If) and ast.unparse(node.test).endswith("TYPE_CHECKING"):
            top |= set(map(id, node.body))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_pkg else module.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "metadesign":
                names = [a.name for a in node.names]
                if target == "metadesign" or (node.module is None and node.level):
                    # ``from . import cli``: the names are submodules
                    subs = [n for n in names if (PKG.parent / target.replace(".", "/") / n).exists()
                            or (PKG.parent / target.replace(".", "/") / f"{n}.py").exists()]
                    for n in subs:
                        out.append((node.lineno, f"{target}.{n}", [], id(node) in top))
                    names = [n for n in names if n not in subs]
                    if not names:
                        continue
                out.append((node.lineno, target, names, id(node) in top))
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "metadesign":
                    out.append((node.lineno, a.name, [], id(node) in top))
    return out


def violations(source: str, module: str, is_pkg: bool = False) -> list[str]:
    own = level(module)
    last = module.split(".")[-1]
    cli = last in TOP or last.startswith("cli_")  # a stage's CLI module, or one of the studies' per-area ones
    bad = []
    for line, target, names, at_top in internal_imports(source, module, is_pkg):
        if target == module:
            continue
        lv = level(target)
        if lv > own:
            bad.append(f"{module}:{line} imports the later {target}")
        if own == 0 and lv != 0:
            bad.append(f"{module}:{line}: a shared edge imports the stage {target}")
        if package_of(target) != package_of(module):
            priv = [n for n in names if n.startswith("_") and n != "__version__"]
            priv += [p for p in target.split(".")[1:] if p.startswith("_") and p != "__init__"]
            if priv:
                bad.append(f"{module}:{line} imports the private {', '.join(priv)} of {target}")
        if not at_top and not cli:
            bad.append(f"{module}:{line}: function-local import of {target} (imports sit at module top)")
    return bad


def test_every_internal_import_resolves():
    """A relative import that points nowhere (e.g. left behind by a move) fails here, not in a user's run."""
    bad = []
    for path, module, is_pkg in all_modules():
        for line, target, _names, _top in internal_imports(path.read_text(), module, is_pkg):
            f = PKG.parent / target.replace(".", "/")
            if not (f.with_suffix(".py").is_file() or (f / "__init__.py").is_file()):
                bad.append(f"{module}:{line}: no module {target}")
    assert not bad, "\n".join(bad)


def all_modules():
    for path in sorted(PKG.rglob("*.py")):
        yield path, *module_name(path)


def test_every_module_respects_the_layers():
    bad = []
    for path, module, is_pkg in all_modules():
        bad += violations(path.read_text(), module, is_pkg)
    assert not bad, "\n".join(bad)


def test_every_subpackage_is_placed():
    for p in PKG.iterdir():
        if p.is_dir() and (p / "__init__.py").exists():
            assert p.name in ORDER, p
        elif p.suffix == ".py" and p.stem != "__init__":
            assert p.stem in EDGES | TOP, p


@pytest.mark.parametrize("module,source,expect", [
    ("metadesign.library.build", "from ..sensing.model import AsFabricated\n", "imports the later"),
    ("metadesign.sensing.model", "def f():\n    from ..reconstruction import data\n", "imports the later"),
    ("metadesign.reconstruction.captures", "from ..sensing.sensor import _resample\n", "private _resample"),
    ("metadesign.reconstruction.captures", "def f():\n    from ..sensing.sensor import psf_tensor\n",
     "function-local"),
    ("metadesign.io", "from .sensing import forward\n", "shared edge"),
    ("metadesign.turbulence.chain", "from metadesign.studies.compare import run_compare\n", "imports the later"),
])
def test_the_checker_catches_violations(module, source, expect):
    """The checker itself: each kind of violation is reported (a test that cannot fail is a defect)."""
    assert any(expect in v for v in violations(source, module)), violations(source, module)


def test_the_checker_accepts_downward_imports():
    assert violations("from ..sensing.forward import CoarsePupil\nfrom ..io import read_npz\n",
                      "metadesign.reconstruction.dataset") == []
    assert violations("def f():\n    from .dataset import build_dataset\n", "metadesign.reconstruction.cli") == []


def test_help_imports_no_heavy_library():
    """``metadesign --help`` builds every parser without importing scipy, torch, zarr, dask or matplotlib
    (subpackages export lazily, PEP 562); and the estimator names it prints are the registry's."""
    import subprocess
    import sys

    code = ("import sys, metadesign.cli as c; c.build_parser(); "
            "print(sorted(m for m in ('scipy', 'torch', 'zarr', 'dask', 'matplotlib', 'klayout', 'onnx') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out
    from metadesign.studies.cli import BUILTIN_ESTIMATORS
    from metadesign.studies.compare import ESTIMATORS

    assert tuple(ESTIMATORS[:len(BUILTIN_ESTIMATORS)]) == BUILTIN_ESTIMATORS


def test_a_core_install_says_what_it_lacks(tmp_path):
    """A command that needs the `learn` extra on a core install (torch missing) is one line naming it."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['torch'] = None; from metadesign.cli import main; "
            f"sys.exit(main(['export', {str(tmp_path / 'm.safetensors')!r}, '-o', {str(tmp_path / 'm.onnx')!r}]))")
    (tmp_path / "m.safetensors").write_bytes(b"x")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    err = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(err) == 1 and "metadesign[learn]" in err[0], p.stderr


def test_the_forward_model_and_the_coupling_cards_import_without_torch():
    """#31: the coupling network is a torch module at module level (library.coupling_net); the forward
    model and the coupling model's numpy side (cards, LPA, look-ups) import on a core install."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['torch'] = None; "
            "import metadesign.sensing.model, metadesign.sensing.transmission, metadesign.library.coupling; "
            "import metadesign.library as L; L.lpa_t; L.coupling_card; print('ok')")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stderr[-1500:]
    import inspect

    from metadesign.library.coupling_net import Coupling

    assert inspect.getmodule(Coupling).__name__ == "metadesign.library.coupling_net"  # not a closure's class


def test_no_undefined_or_shadowed_names():
    """pyflakes' checks (through ruff) on the package, the tests and the benchmarks: an undefined name (a
    variable a refactor removed), a redefinition, an unused variable; unused imports are allowed (import
    checks of optional dependencies)."""
    import shutil
    import subprocess
    import sys

    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not Path(ruff).exists():
        pytest.skip("ruff is not installed (pip install -e .[test])")
    root = PKG.parent
    p = subprocess.run([ruff, "check", "--no-cache", "--select", "F", "--ignore", "F401", "--output-format",
                        "concise", "metadesign", "tests", "benchmarks"], cwd=root, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-1000:]
