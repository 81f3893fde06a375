"""Start-up and product-layer benchmark.

Prints ``metadesign --help`` wall time (min of 7 runs, a fresh interpreter each) against a bare
``python -c pass`` and ``import numpy`` measured in the same run; the modules ``--help`` imports; the cost
of the product layer's checks (an output declared against 8 inputs, an existing product identified) and
of the resumable-task engine per task (1,000 trivial tasks kept as JSON markers).  Goal: ``--help`` <=
0.3 s (issue #31; 1.0 s idle before the lazy subpackage exports).

    python benchmarks/bench_cli.py [--json]
"""

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
ENV = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(REPO))


def wall(args, n=7) -> float:
    best = float("inf")
    for _ in range(n):
        t = time.perf_counter()
        subprocess.run(args, env=ENV, check=True, capture_output=True)
        best = min(best, time.perf_counter() - t)
    return best


def _task(x):
    return f"t{x:06d}", {"x": x}


def main() -> None:
    as_json = "--json" in sys.argv
    py = sys.executable
    rep = {"python_pass_s": wall([py, "-c", "pass"]), "import_numpy_s": wall([py, "-c", "import numpy"]),
           "help_s": wall([py, "-m", "metadesign", "--help"])}
    code = ("import sys, metadesign.cli as c; c.build_parser(); "
            "print(len([m for m in sys.modules if m.startswith('metadesign')]), "
            "sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'torch', 'zarr', 'dask', 'matplotlib', "
            "'klayout', 'gdstk', 'onnx'}))")
    out = subprocess.run([py, "-c", code], env=ENV, check=True, capture_output=True, text=True).stdout.split(" ", 1)
    rep["help_metadesign_modules"], rep["help_heavy_imports"] = int(out[0]), out[1].strip()

    from metadesign.outputs import check_output, identify
    from metadesign.tasks import TaskFolder, run_resumable

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ins = {f"in{i}": tmp / f"in{i}.toml" for i in range(8)}
        t = time.perf_counter()
        for _ in range(1000):
            check_output(tmp / "out", "design", ins)
        rep["check_output_us"] = (time.perf_counter() - t) * 1e3
        lib = REPO / "library" / "paper.npz"
        t = time.perf_counter()
        for _ in range(100):
            identify(lib)
        rep["identify_npz_ms"] = (time.perf_counter() - t) * 10
        folder = TaskFolder(tmp / "tasks", key="k")
        t = time.perf_counter()
        run_resumable(_task, {f"t{i:06d}": i for i in range(1000)}, folder, store="marker")
        rep["engine_per_task_ms"] = (time.perf_counter() - t)
        t = time.perf_counter()
        _, computed = run_resumable(_task, {f"t{i:06d}": i for i in range(1000)}, folder, store="marker")
        rep["engine_resume_per_task_ms"] = (time.perf_counter() - t)
        assert not computed
    rep["help_over_import_numpy"] = rep["help_s"] / rep["import_numpy_s"]
    if as_json:
        print(json.dumps(rep, indent=2))
        return
    print(f"metadesign --help          {rep['help_s'] * 1e3:6.0f} ms (goal <= 300 ms); python -c pass "
          f"{rep['python_pass_s'] * 1e3:.0f} ms, import numpy {rep['import_numpy_s'] * 1e3:.0f} ms "
          f"(--help / import numpy = {rep['help_over_import_numpy']:.2f}x)")
    print(f"  imports {rep['help_metadesign_modules']} metadesign modules; heavy libraries: {rep['help_heavy_imports']}")
    print(f"product layer: check_output (8 inputs) {rep['check_output_us']:.0f} us, identify a library "
          f"{rep['identify_npz_ms']:.2f} ms")
    print(f"task engine: {rep['engine_per_task_ms']:.2f} ms per task kept, {rep['engine_resume_per_task_ms']:.3f} ms per "
          "task found done on resume")


if __name__ == "__main__":
    main()
