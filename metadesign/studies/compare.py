"""``metadesign compare`` / ``retrieve``: every wavefront sensor on the same samples.

Per sample of a dataset split, with the same sensor noise for every method (Gaussian, % of the peak of
each frame, seeded per sample): NPiB of the uncorrected beam, the simulated Shack-Hartmann sensor, the
model-based phase-diversity retrieval, the U-Net, the hybrid (retrieval started from the U-Net), and the
phase and complex conjugates of the true received field (the oracle bounds), all with the bucket and
normalisation of the turbulence stage (:class:`~metadesign.reconstruction.losses.PiB`).

Latency is measured on one sample at a time on this machine (one thread), from the input a method sees
(the PSF tensor; the Shack-Hartmann spot frame) to its phase estimate.  The iterative methods' NPiB is
recorded at checkpoints along their iterations, so each has an NPiB-vs-latency curve; "at budget b" a
method delivers the best estimate it has by then (nothing: the uncorrected beam).  The retrieval's quality
does not depend on the batch it runs in (Adam is elementwise), so curves from batched runs and latency
from single-sample runs describe the same computation.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..cliutil import json_safe
from ..io import atomic_path, atomic_write_text
from ..parallel import WorkerPool
from ..plotting import pyplot, save_figure
from ..reconstruction.data import PSFDataset
from ..reconstruction.estimators import ESTIMATORS as ESTIMATOR_CLASSES
from ..reconstruction.estimators import HybridEstimator, checkpoints_for, estimator_names, make_estimator, sh_exposures
from ..reconstruction.evaluate import RYTOV_BINS
from ..reconstruction.losses import PiB
from ..reconstruction.metrics import EVAL_NOISE_SEED, npib_rows
from ..reconstruction.model import check_fits, load_model
from ..reconstruction.refine import is_refiner, load_refiner
from ..reconstruction.retrieval import RetrievalConfig
from ..reconstruction.shack_hartmann import SHConfig
from ..timing import repeat_seconds
from ..validation import ConfigError, ValidationError

__all__ = ["CompareSettings", "run_compare", "tune", "summarise", "write_compare", "checkpoints_for",
           "at_budget", "BUDGETS_MS", "methods", "label", "style"]

#: the registered estimators (metadesign.reconstruction.estimators), in registration order, at import; the
#: functions below read the registry live, so an estimator registered later takes part too
ESTIMATORS = estimator_names()
BUDGETS_MS = (1.0, 10.0, 100.0)
_FIXED = {"none": ("uncorrected", ("k", "x")), "phase_conjugate": ("phase conjugate (oracle)", ("tab:green", "s")),
          "complex_conjugate": ("complex conjugate (oracle)", ("tab:olive", "^"))}


def methods() -> tuple[str, ...]:
    """Every row of a comparison: the uncorrected beam, the estimators, the oracle bounds."""
    return ("none", *estimator_names(), "phase_conjugate", "complex_conjugate")


def label(m: str) -> str:
    return _FIXED[m][0] if m in _FIXED else ESTIMATOR_CLASSES[m].label


def style(m: str) -> tuple[str, str]:
    return _FIXED[m][1] if m in _FIXED else ESTIMATOR_CLASSES[m].style



@dataclass(frozen=True)
class CompareSettings:
    split: str = "test"
    limit: int | None = None
    noise_percent: float = 5.0
    noise_seed: int = EVAL_NOISE_SEED
    batch: int = 8
    methods: tuple[str, ...] = ESTIMATORS
    retrieval: RetrievalConfig = field(default_factory=lambda: RetrievalConfig(misfit="gaussian"))
    hybrid: RetrievalConfig = HybridEstimator.DEFAULT  # from the U-Net
    sh: SHConfig = field(default_factory=lambda: SHConfig(lenslets=5, threshold=0.3, noise_sigmas=3.0))
    latency_samples: int = 2

    def __post_init__(self):
        bad = [m for m in self.methods if m not in estimator_names()]
        if bad:
            raise ConfigError("methods", f"expected some of {', '.join(estimator_names())}, got {', '.join(bad)}")
        # the retrieval's Gaussian likelihood uses the noise level of the data
        for k in ("retrieval", "hybrid", "sh"):  # ... and the Shack-Hartmann centroid threshold
            object.__setattr__(self, k, replace(getattr(self, k), noise_percent=self.noise_percent))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["methods"] = list(self.methods)
        return d


def _batch_of(items: list[dict]) -> dict:
    return {"psf": np.stack([s["psf"] for s in items]), "received": np.stack([s["received"] for s in items]),
            "index": np.array([s["index"] for s in items])}


def _exposed(est, batch: dict, st: "CompareSettings") -> dict:
    """``batch`` with what ``est``'s own sensor recorded (a Shack-Hartmann's spots, through its detector at the
    study's noise), when it has one; the metasurface's PSFs came with the dataset's detector."""
    if not est.own_sensor:
        return batch
    return {**batch, "sh_spots": sh_exposures(est, batch["received"], batch["index"], st.noise_percent,
                                              st.noise_seed)}


class _Runner:
    """Everything one process needs (built lazily in each worker): the dataset split with its sensor noise,
    the bucket, and the estimators (:mod:`metadesign.reconstruction.estimators`) of the settings."""

    def __init__(self, model, dataset, st: CompareSettings):
        import torch

        torch.set_num_threads(1)
        self.st = st
        self.ds = PSFDataset(dataset, st.split, gaussian_percent=st.noise_percent, noise_seed=st.noise_seed,
                             limit=st.limit, screens=True)
        self.dev = dev = self.ds.device()
        self.pib = PiB(self.ds.scenario(), dev.crop.start, dev.crop.size)
        self.model, self.refiner, self.card = _models(model)
        self.est = {name: make_estimator(name, dev, st, self.model, self.refiner)
                    for name in _run_order(st.methods, self.model is not None, self.refiner is not None)}

    def items(self, js):
        return [self.ds.get(j) for j in js]

    def batch(self, js) -> dict:
        import torch

        items = self.items(js)
        scr = torch.from_numpy(np.stack([s["screens"] for s in items]))
        rec = torch.from_numpy(np.stack([s["received"] for s in items]))
        pib = self.pib
        r = {"index": np.array([s["index"] for s in items]), "rytov": np.array([s["rytov"] for s in items]),
             "rytov_measured": np.array([s["rytov_measured"] for s in items])}

        def npib(phi):
            with torch.no_grad():
                return pib.npib_phase(torch.as_tensor(phi), scr).numpy()

        ref = npib_rows(pib, torch.zeros(rec.shape, dtype=torch.float32), scr, rec, complex_conjugate=True)
        for k in ("none", "phase_conjugate", "complex_conjugate"):
            r[k] = ref[k].numpy()
        batch = _batch_of(items)
        done: dict = {}
        for name, est in self.est.items():
            if est.iterations is None:
                done[name] = est.estimate(_exposed(est, batch, self.st), done)
                r[name] = npib(done[name])
                continue
            cks, curve = est.checkpoints(), {}
            done[name] = est.estimate(batch, done, on_checkpoint=lambda it, phi: curve.__setitem__(it, npib(phi)))
            r[f"{name}_curve"] = np.stack([curve[c] for c in cks])  # (n_checkpoints, B)
            r[name] = r[f"{name}_curve"][-1]
            if est.misfit() is not None:
                r[f"{name}_misfit"] = est.misfit()  # (iterations, B)
        return r

    def latency(self) -> dict:
        """Single-sample latency (ms) of each estimator, from the input it sees to its phase estimate; for
        the iterative ones, at each checkpoint (plus the latency of the estimator they start from)."""
        items = self.items(range(min(self.st.latency_samples, len(self.ds))))
        out: dict = {}
        for name, est in self.est.items():
            base = out.get(est.starts_from, 0.0)
            if est.iterations is None:
                out[name] = 1e3 * repeat_seconds(est.latency_fn(_exposed(est, _batch_of(items[:1]), self.st)), 15)
                continue
            cks, runs = est.checkpoints(), []
            for s in items:
                one = _batch_of([s])
                done = {est.starts_from: self.est[est.starts_from].estimate(one)} if est.starts_from else {}
                stamps: dict = {}
                t0 = time.perf_counter()
                est.estimate(one, done, on_checkpoint=lambda it, phi: stamps.__setitem__(it, time.perf_counter()))
                runs.append([base + 1e3 * (stamps[c] - t0) for c in cks])
            out[f"{name}_curve"] = np.median(np.array(runs), axis=0)
            out[name] = float(out[f"{name}_curve"][-1])
        return out


def _models(model) -> tuple:
    """(U-Net, refiner or None, card) of a study's model argument: U-Net weights, or a refiner (which
    brings its U-Net), or None."""
    if model is None:
        return None, None, None
    if is_refiner(model):
        ref, card = load_refiner(model)
        return ref.unet, ref, card
    unet, card = load_model(model)
    return unet, None, card


def _run_order(methods, have_model: bool, have_refiner: bool = False) -> list[str]:
    """The estimators to run, in registry order: the asked ones the model allows, and those they start from
    (the hybrid's U-Net: recorded too)."""
    want = {m for m in methods if (have_model or not ESTIMATOR_CLASSES[m].needs_model)
            and (have_refiner or not ESTIMATOR_CLASSES[m].needs_refiner)}
    want |= {ESTIMATOR_CLASSES[m].starts_from for m in list(want)} - {None}
    return [m for m in ESTIMATOR_CLASSES if m in want]


_RUNNER = None


def _worker_batch(args):
    global _RUNNER
    model, dataset, st, js = args
    if _RUNNER is None:
        _RUNNER = _Runner(model, dataset, st)
    return _RUNNER.batch(js)


def run_compare(model, dataset, st: CompareSettings, workers: int = 1,
                progress: Callable[[int, int], None] | None = None) -> dict:
    """Per-sample NPiB of every method, curves and latency (see the module docstring)."""
    if model is None:
        dropped = [m for m in st.methods if ESTIMATOR_CLASSES[m].needs_model]
        st = replace(st, methods=tuple(m for m in st.methods if m not in dropped))
        if dropped and not st.methods:
            raise ValidationError(f"--methods: {' and '.join(dropped)} need a model, and MODEL is NONE: nothing to run")
    runner = _Runner(model, dataset, st)
    n = len(runner.ds)
    if n == 0:
        raise ValidationError(f"{dataset}: the {st.split} split is empty")
    if runner.model is not None:
        check_fits(runner.model, runner.ds.info, str(model))
    chunks = [list(range(i, min(n, i + st.batch))) for i in range(0, n, st.batch)]
    t0 = time.perf_counter()
    parts = []
    if workers > 1 and len(chunks) > 1:
        with WorkerPool(min(workers, len(chunks))) as pool:
            for k, r in enumerate(pool.map(_worker_batch, [(model, dataset, st, js) for js in chunks], ordered=True)):
                parts.append(r)
                if progress:
                    progress(sum(len(c) for c in chunks[:k + 1]), n)
    else:
        for k, js in enumerate(chunks):
            parts.append(runner.batch(js))
            if progress:
                progress(sum(len(c) for c in chunks[:k + 1]), n)
    wall = time.perf_counter() - t0
    rows = {}
    for key in parts[0]:
        ax = 1 if (key.endswith("_curve") or key.endswith("_misfit")) else 0
        rows[key] = np.concatenate([p[key] for p in parts], axis=ax)
    lat = runner.latency()
    return {"rows": rows, "latency_ms": lat, "n": n, "wall_seconds": wall, "settings": st,
            "checkpoints": {m: e.checkpoints() for m, e in runner.est.items() if f"{m}_curve" in rows},
            "card": getattr(runner, "card", None)}


# -- summaries --------------------------------------------------------------------------------------

def methods_present(rows: dict) -> list[str]:
    return [m for m in methods() if m in rows]


def at_budget(res: dict, method: str, budget_ms: float) -> np.ndarray:
    """Per-sample NPiB a method delivers within ``budget_ms`` (the uncorrected beam when it has nothing)."""
    rows, lat = res["rows"], res["latency_ms"]
    if method == "none":
        return rows["none"]
    if f"{method}_curve" in rows:
        t = np.asarray(lat[f"{method}_curve"])
        ok = np.nonzero(t <= budget_ms)[0]
        return rows[f"{method}_curve"][ok[-1]] if len(ok) else rows["none"]
    return rows[method] if lat.get(method, np.inf) <= budget_ms else rows["none"]


def summarise(res: dict) -> dict:
    rows = res["rows"]
    ms = methods_present(rows)
    x = rows["rytov_measured"]
    out = {"n": res["n"], "npib": {m: float(np.mean(rows[m])) for m in ms},
           "npib_median": {m: float(np.median(rows[m])) for m in ms},
           "latency_ms": {m: float(res["latency_ms"][m]) for m in ms if m in res["latency_ms"]},
           "by_rytov": {}, "budgets_ms": {}, "curves": {}}
    for lo, hi in zip(RYTOV_BINS[:-1], RYTOV_BINS[1:]):
        m = (x >= lo) & (x < hi)
        if m.any():
            out["by_rytov"][f"{lo:g}-{hi:g}"] = {"n": int(m.sum()), **{k: float(np.mean(rows[k][m])) for k in ms}}
    for b in BUDGETS_MS:
        out["budgets_ms"][f"{b:g}"] = {k: float(np.mean(at_budget(res, k, b))) for k in ms
                                        if k not in ("phase_conjugate", "complex_conjugate")}
    for k, cks in res.get("checkpoints", {}).items():
        out["curves"][k] = [{"iterations": c, "latency_ms": float(t), "npib": float(np.mean(v))}
                            for c, t, v in zip(cks, res["latency_ms"][f"{k}_curve"], rows[f"{k}_curve"])]
    return out


def write_compare(res: dict, out: Path, tuning: dict | None = None, made_with: dict | None = None) -> list[Path]:
    """compare.csv (per sample), compare-curves.csv, compare.json (with ``made_with``: the model and dataset
    it was computed from, :mod:`metadesign.studies.madewith`), and the figures."""
    out.mkdir(parents=True, exist_ok=True)
    rows = res["rows"]
    ms = methods_present(rows)
    files = []
    p = out / "compare.csv"
    with atomic_path(p) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["index", "rytov", "rytov_measured"] + ms)
            for i in range(res["n"]):
                w.writerow([int(rows["index"][i]), f"{rows['rytov'][i]:.5g}", f"{rows['rytov_measured'][i]:.5g}"]
                           + [f"{rows[m][i]:.6g}" for m in ms])
    files.append(p)
    summ = summarise(res)
    p = out / "compare-curves.csv"
    with atomic_path(p) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["method", "iterations", "latency_ms", "npib_mean"])
            for m in ms:
                if m in summ["curves"]:
                    for c in summ["curves"][m]:
                        w.writerow([m, c["iterations"], f"{c['latency_ms']:.4g}", f"{c['npib']:.6g}"])
                elif m in summ["latency_ms"]:
                    w.writerow([m, "", f"{summ['latency_ms'][m]:.4g}", f"{summ['npib'][m]:.6g}"])
    files.append(p)
    files += plot_compare(res, summ, out)
    doc = {"summary": summ, "settings": res["settings"].to_dict(), "wall_seconds": res["wall_seconds"],
           "tuning": tuning, "made_with": made_with, "files": [str(f) for f in files] + [str(out / "compare.json")]}
    atomic_write_text(out / "compare.json", json.dumps(json_safe(doc), indent=2, sort_keys=True))
    files.append(out / "compare.json")
    return files


def plot_compare(res: dict, summ: dict, out: Path) -> list[Path]:
    plt = pyplot()
    rows = res["rows"]
    ms = methods_present(rows)
    figs = []
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 4.8), constrained_layout=True)
    x = rows["rytov_measured"]
    edges = np.quantile(x, np.linspace(0, 1, min(6, max(2, res["n"] // 8)) + 1)) if res["n"] > 1 else \
        np.array([x.min(), x.max() + 1e-9])
    edges[-1] += 1e-9
    for m in ms:
        c, mk = style(m)
        a1.scatter(x, rows[m], s=6, color=c, alpha=0.25, marker=mk)
        mids, means, sems = [], [], []
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (x >= lo) & (x < hi)
            if sel.sum():
                mids.append(np.mean(x[sel]))
                means.append(np.mean(rows[m][sel]))
                sems.append(np.std(rows[m][sel]) / np.sqrt(sel.sum()))
        a1.errorbar(mids, means, sems, color=c, marker=mk, label=f"{label(m)} ({np.mean(rows[m]):.3f})", capsize=2)
    a1.set(xlabel="Rytov number of the sample (measured)", ylabel="NPiB",
           title=f"{res['n']} {res['settings'].split} samples, noise {res['settings'].noise_percent:g} %")
    a1.legend(fontsize=7)
    lat = res["latency_ms"]
    for m in ms:
        c, mk = style(m)
        if m in summ["curves"]:
            cv = summ["curves"][m]
            a2.semilogx([max(p["latency_ms"], 1e-2) for p in cv], [p["npib"] for p in cv], "-", color=c, marker=mk,
                        ms=4, label=label(m))
        elif m in lat:
            a2.semilogx([lat[m]], [summ["npib"][m]], mk, color=c, ms=9, label=f"{label(m)} ({lat[m]:.2g} ms)")
        else:
            a2.axhline(summ["npib"][m], color=c, ls=":" if m == "none" else "--", lw=1, label=label(m))
    for b in BUDGETS_MS:
        a2.axvline(b, color="0.7", lw=0.8)
    a2.set(xlabel="latency per sample [ms] (one CPU thread)", ylabel="mean NPiB", title="NPiB vs latency")
    a2.legend(fontsize=7)
    figs.append(save_figure(fig, out / "compare.png"))
    return figs


# -- tuning -----------------------------------------------------------------------------------------

SH_GRID = {"lenslets": (4, 5, 8, 10), "reconstructor": ("zonal", "modal"), "threshold": (0.1, 0.3),
           "noise_sigmas": (0.0, 3.0)}
RETRIEVAL_GRID = {"misfit": ("gaussian", "amplitude"), "lr_zonal": (0.03, 0.1)}
HYBRID_GRID = {"misfit": ("gaussian", "amplitude"), "lr_zonal": (0.01, 0.03, 0.1)}
#: what ``--tune`` searches, by estimator (an estimator without a grid is used as configured)
TUNING_GRIDS = {"shack_hartmann": SH_GRID, "retrieval": RETRIEVAL_GRID, "hybrid": HYBRID_GRID}


def _grid(base, grid: dict):
    import itertools

    keys = list(grid)
    for vals in itertools.product(*(grid[k] for k in keys)):
        yield replace(base, **dict(zip(keys, vals)))


def tune(model, dataset, st: CompareSettings, n: int, split: str = "val", log=print) -> tuple[CompareSettings, dict]:
    """Tune each baseline as its user would, on ``n`` samples of ``split`` (never the compared split):
    the Shack-Hartmann geometry, centroiding and reconstructor, the retrieval's misfit and step, the
    hybrid's misfit and step (each at its own iteration count); returns the settings with the winners."""
    import torch

    methods = st.methods if model is not None else tuple(m for m in st.methods if not ESTIMATOR_CLASSES[m].needs_model)
    probe = replace(st, split=split, limit=n, methods=())
    base = _Runner(None, dataset, probe)
    items = base.items(range(min(n, len(base.ds))))
    if not items:
        return st, {}
    scr = torch.from_numpy(np.stack([s["screens"] for s in items]))

    def npib(phi):
        with torch.no_grad():
            return float(base.pib.npib_phase(torch.as_tensor(phi), scr).mean())

    report: dict = {"split": split, "samples": len(items)}
    batch = _batch_of(items)
    done: dict = {}
    mdl = refiner = None
    starts = {ESTIMATOR_CLASSES[m].starts_from for m in methods} - {None}
    if model is not None and starts:
        mdl, refiner, _ = _models(model)
        done = {s: make_estimator(s, base.dev, model=mdl).estimate(batch) for s in starts}
    for name in _run_order(methods, model is not None, refiner is not None):
        cls = ESTIMATOR_CLASSES[name]
        grid = TUNING_GRIDS.get(name)
        if not grid or (cls.starts_from and cls.starts_from not in done):
            continue
        table = []
        for cfg in _grid(getattr(st, cls.config_key), grid):
            est = cls(base.dev, cfg, mdl)
            table.append((npib(est.estimate(_exposed(est, batch, st), done)), cfg))
        best = max(table, key=lambda t: t[0])
        st = replace(st, **{cls.config_key: best[1]})
        report[name] = {"best": best[1].to_dict(), "npib": best[0],
                        "table": [{**({k: getattr(c, k) for k in grid} if name != "shack_hartmann" else c.to_dict()),
                                   "npib": v} for v, c in table]}
        log(f"tuned {cls.label if name == 'shack_hartmann' else name}: {best[0]:.3f} with "
            + (str(best[1]) if name == "shack_hartmann" else ", ".join(f"{k}={getattr(best[1], k)}" for k in grid)))
    return st, report
