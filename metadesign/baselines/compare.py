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

from .retrieval import RetrievalConfig
from .shack_hartmann import SHConfig

__all__ = ["CompareSettings", "run_compare", "device_of", "tune", "summarise", "write_compare", "checkpoints_for",
           "at_budget", "METHODS", "BUDGETS_MS"]

METHODS = ("none", "shack_hartmann", "retrieval", "unet", "hybrid", "phase_conjugate", "complex_conjugate")
ESTIMATORS = ("shack_hartmann", "retrieval", "unet", "hybrid")
BUDGETS_MS = (1.0, 10.0, 100.0)
LABELS = {"none": "uncorrected", "shack_hartmann": "Shack-Hartmann", "retrieval": "PD retrieval",
          "unet": "U-Net", "hybrid": "U-Net + retrieval", "phase_conjugate": "phase conjugate (oracle)",
          "complex_conjugate": "complex conjugate (oracle)"}

HYBRID_DEFAULT = RetrievalConfig(modal_iterations=0, zonal_iterations=50, lr_zonal=0.03, misfit="gaussian")  # from the U-Net


@dataclass(frozen=True)
class CompareSettings:
    split: str = "test"
    limit: int | None = None
    noise_percent: float = 5.0
    noise_seed: int = 12345
    batch: int = 8
    methods: tuple[str, ...] = ESTIMATORS
    retrieval: RetrievalConfig = field(default_factory=lambda: RetrievalConfig(misfit="gaussian"))
    hybrid: RetrievalConfig = HYBRID_DEFAULT
    sh: SHConfig = field(default_factory=lambda: SHConfig(lenslets=5, threshold=0.3, noise_sigmas=3.0))
    latency_samples: int = 2

    def __post_init__(self):
        from ..validation import ConfigError

        bad = [m for m in self.methods if m not in ESTIMATORS]
        if bad:
            raise ConfigError("methods", f"expected some of {', '.join(ESTIMATORS)}, got {', '.join(bad)}")
        # the retrieval's Gaussian likelihood uses the noise level of the data
        for k in ("retrieval", "hybrid"):
            object.__setattr__(self, k, replace(getattr(self, k), noise_percent=self.noise_percent))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["methods"] = list(self.methods)
        return d


def checkpoints_for(total: int) -> list[int]:
    """0, 1, 2, 5, 10, 20, 50, ... up to ``total`` (and ``total``)."""
    out, base = [0], 1
    while base <= total:
        out += [c for c in (base, 2 * base, 5 * base) if c <= total]
        base *= 10
    return sorted(set(out + [total]))


def device_of(dataset: str | Path) -> dict:
    """The device a dataset was made with: its coarse pupil (cached in the store), sensor and crop geometry."""
    from ..io import read_npz
    from ..reconstruction.data import PSFDataset
    from ..sensing.forward import CoarsePupil
    from ..sensing.sensor import SensorSpec
    from ..validation import ValidationError

    ds = PSFDataset(dataset, "all", limit=1)
    prov = ds.info.attrs["provenance"]
    path = Path(dataset) / "device-pupil.npz"
    if not path.is_file():
        if ds.info.attrs.get("propagation") == "slm":
            raise ValidationError(f"{dataset}: imported captures carry no device model (the forward model of "
                                  "compare / retrieve / synth-captures needs a synthetic dataset)")
        raise ValidationError(f"{path}: missing (the device's coarse pupil, written by `metadesign dataset build`)")
    z = read_npz(path, "device pupil")
    cp = CoarsePupil(z["G"], z["X"], int(z["block"]), float(z["period"]), float(z["wavelength"]), float(z["z"]),
                     int(z["n_clamped"]))
    s = prov["sensor"]
    sensor = SensorSpec(int(s["width_px"]), int(s["height_px"]), float(s["pixel_um"]) * 1e-6,
                        float(s["magnification"]), float(s["distance_mm"]) * 1e-3, int(ds.info.tensor_size))
    sc = ds.scenario()
    c0, a = ds.crop()
    return {"pupil": cp, "sensor": sensor, "scenario": sc, "crop": (c0, a),
            "geometry": (c0, a, sc.n_grid, sc.dx, sc.receiver_aperture)}


class _Runner:
    """Everything one process needs (built lazily in each worker)."""

    def __init__(self, model, dataset, st: CompareSettings):
        import torch

        from ..reconstruction.data import PSFDataset
        from ..reconstruction.losses import PiB
        from .retrieval import RetrievalContext
        from .shack_hartmann import ShackHartmann

        torch.set_num_threads(1)
        self.st = st
        dev = device_of(dataset)
        self.dev = dev
        sc = dev["scenario"]
        c0, a = dev["crop"]
        self.ds = PSFDataset(dataset, st.split, gaussian_percent=st.noise_percent, noise_seed=st.noise_seed,
                             limit=st.limit, screens=True)
        self.pib = PiB(sc, c0, a)
        self.model = None
        if model is not None:
            from ..reconstruction.model import load_model

            self.model, self.card = load_model(model)
        self.ctx = RetrievalContext.build(dev["pupil"], dev["sensor"], dev["geometry"], st.retrieval) \
            if "retrieval" in st.methods else None
        self.hctx = RetrievalContext.build(dev["pupil"], dev["sensor"], dev["geometry"], st.hybrid) \
            if "hybrid" in st.methods else None
        self.sh = ShackHartmann(st.sh, a, c0, sc.n_grid, sc.dx, sc.receiver_aperture, sc.wavelength) \
            if "shack_hartmann" in st.methods else None

    def items(self, js):
        return [self.ds.get(j) for j in js]

    def sh_rng(self, index: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence(self.st.noise_seed, spawn_key=(7, int(index))))

    def sh_phase(self, items) -> np.ndarray:
        out = []
        for s in items:
            spots = self.sh.add_noise(self.sh.frames(s["received"][None]), self.st.noise_percent,
                                      self.sh_rng(s["index"]))
            out.append(self.sh.reconstruct(*self.sh.centroids(spots, self.st.noise_percent))[0])
        return np.stack(out)

    def batch(self, js) -> dict:
        import torch

        from .retrieval import retrieve

        st = self.st
        items = self.items(js)
        psf = torch.from_numpy(np.stack([s["psf"] for s in items]))
        scr = torch.from_numpy(np.stack([s["screens"] for s in items]))
        rec = torch.from_numpy(np.stack([s["received"] for s in items]))
        pib = self.pib
        r = {"index": np.array([s["index"] for s in items]), "rytov": np.array([s["rytov"] for s in items]),
             "rytov_measured": np.array([s["rytov_measured"] for s in items])}

        def npib(phi):
            with torch.no_grad():
                return pib.npib_phase(phi, scr).numpy()

        with torch.no_grad():
            r["none"] = npib(torch.zeros(rec.shape, dtype=torch.float32))
            r["phase_conjugate"] = npib(torch.angle(rec) * pib.ap)
            r["complex_conjugate"] = pib.npib_complex(rec, scr).numpy()
        phi_u = None
        if self.model is not None and ("unet" in st.methods or "hybrid" in st.methods):
            with torch.no_grad():
                phi_u = self.model(psf)
            r["unet"] = npib(phi_u)
        if self.sh is not None:
            r["shack_hartmann"] = npib(torch.from_numpy(self.sh_phase(items)))
        for name, ctx, cfg, init in (("retrieval", self.ctx, st.retrieval, None),
                                     ("hybrid", self.hctx, st.hybrid, phi_u)):
            if ctx is None or (name == "hybrid" and phi_u is None):
                continue
            cks = checkpoints_for(cfg.iterations)
            curve = {}
            out = retrieve(psf, ctx, cfg, init=init, checkpoints=cks,
                           on_checkpoint=lambda it, phi: curve.__setitem__(it, npib(phi)))
            r[f"{name}_curve"] = np.stack([curve[c] for c in cks])  # (n_checkpoints, B)
            r[name] = r[f"{name}_curve"][-1]
            r[f"{name}_misfit"] = out["misfit"]  # (iterations, B)
        return r

    def latency(self) -> dict:
        """Single-sample latency (ms) of each method; for the iterative ones, at each checkpoint."""
        import torch

        from ..timing import repeat_seconds
        from .retrieval import retrieve

        st = self.st
        items = self.items(range(min(st.latency_samples, len(self.ds))))
        out = {}

        def median_ms(fn):
            return 1e3 * repeat_seconds(fn, 15)

        psf1 = torch.from_numpy(items[0]["psf"][None])
        if self.model is not None:
            with torch.no_grad():
                out["unet"] = median_ms(lambda: self.model(psf1))
        if self.sh is not None:
            spots = self.sh.add_noise(self.sh.frames(items[0]["received"][None]), st.noise_percent, self.sh_rng(0))
            out["shack_hartmann"] = median_ms(lambda: self.sh.reconstruct(*self.sh.centroids(spots, st.noise_percent)))
        for name, ctx, cfg in (("retrieval", self.ctx, st.retrieval), ("hybrid", self.hctx, st.hybrid)):
            if ctx is None or (name == "hybrid" and self.model is None):
                continue
            cks = checkpoints_for(cfg.iterations)
            runs = []
            for s in items:
                p = torch.from_numpy(s["psf"][None])
                init = None
                base = 0.0
                if name == "hybrid":
                    with torch.no_grad():
                        init = self.model(p)
                    base = out["unet"]
                t0 = time.perf_counter()
                stamps = {}
                retrieve(p, ctx, cfg, init=init, checkpoints=cks,
                         on_checkpoint=lambda it, phi: stamps.__setitem__(it, time.perf_counter()))
                runs.append([base + 1e3 * (stamps[c] - t0) for c in cks])
            out[f"{name}_curve"] = np.median(np.array(runs), axis=0)
            out[name] = float(out[f"{name}_curve"][-1])
        return out


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
    from ..parallel import spawn_pool
    from ..validation import ValidationError

    if model is None:
        st = replace(st, methods=tuple(m for m in st.methods if m not in ("unet", "hybrid")))
    runner = _Runner(model, dataset, st)
    n = len(runner.ds)
    if n == 0:
        raise ValidationError(f"{dataset}: the {st.split} split is empty")
    if runner.model is not None and runner.model.config.input_size != runner.ds.info.tensor_size:
        raise ValidationError(f"model input {runner.model.config.input_size}^2 does not match the dataset's "
                              f"tensors ({runner.ds.info.tensor_size}^2)")
    chunks = [list(range(i, min(n, i + st.batch))) for i in range(0, n, st.batch)]
    t0 = time.perf_counter()
    parts = []
    if workers > 1 and len(chunks) > 1:
        with spawn_pool(min(workers, len(chunks))) as pool:
            for k, r in enumerate(pool.imap(_worker_batch, [(model, dataset, st, js) for js in chunks])):
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
            "checkpoints": {m: checkpoints_for(getattr(st, m).iterations) for m in ("retrieval", "hybrid")
                            if f"{m}_curve" in rows},
            "card": getattr(runner, "card", None)}


# -- summaries --------------------------------------------------------------------------------------

def methods_present(rows: dict) -> list[str]:
    return [m for m in METHODS if m in rows]


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
    from ..reconstruction.evaluate import RYTOV_BINS

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


def write_compare(res: dict, out: Path, tuning: dict | None = None) -> list[Path]:
    """compare.csv (per sample), compare-curves.csv, compare.json, and the figures."""
    from ..cliutil import json_safe
    from ..io import atomic_path, atomic_write_text

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
           "tuning": tuning, "files": [str(f) for f in files] + [str(out / "compare.json")]}
    atomic_write_text(out / "compare.json", json.dumps(json_safe(doc), indent=2, sort_keys=True))
    files.append(out / "compare.json")
    return files


def plot_compare(res: dict, summ: dict, out: Path) -> list[Path]:
    from ..plotting import pyplot, save_figure

    plt = pyplot()
    rows = res["rows"]
    ms = methods_present(rows)
    style = {"none": ("k", "x"), "shack_hartmann": ("tab:orange", "v"), "retrieval": ("tab:purple", "D"),
             "unet": ("tab:blue", "o"), "hybrid": ("tab:red", "*"), "phase_conjugate": ("tab:green", "s"),
             "complex_conjugate": ("tab:olive", "^")}
    figs = []
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 4.8), constrained_layout=True)
    x = rows["rytov_measured"]
    edges = np.quantile(x, np.linspace(0, 1, min(6, max(2, res["n"] // 8)) + 1)) if res["n"] > 1 else \
        np.array([x.min(), x.max() + 1e-9])
    edges[-1] += 1e-9
    for m in ms:
        c, mk = style[m]
        a1.scatter(x, rows[m], s=6, color=c, alpha=0.25, marker=mk)
        mids, means, sems = [], [], []
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (x >= lo) & (x < hi)
            if sel.sum():
                mids.append(np.mean(x[sel]))
                means.append(np.mean(rows[m][sel]))
                sems.append(np.std(rows[m][sel]) / np.sqrt(sel.sum()))
        a1.errorbar(mids, means, sems, color=c, marker=mk, label=f"{LABELS[m]} ({np.mean(rows[m]):.3f})", capsize=2)
    a1.set(xlabel="Rytov number of the sample (measured)", ylabel="NPiB",
           title=f"{res['n']} {res['settings'].split} samples, noise {res['settings'].noise_percent:g} %")
    a1.legend(fontsize=7)
    lat = res["latency_ms"]
    for m in ms:
        c, mk = style[m]
        if m in summ["curves"]:
            cv = summ["curves"][m]
            a2.semilogx([max(p["latency_ms"], 1e-2) for p in cv], [p["npib"] for p in cv], "-", color=c, marker=mk,
                        ms=4, label=LABELS[m])
        elif m in lat:
            a2.semilogx([lat[m]], [summ["npib"][m]], mk, color=c, ms=9, label=f"{LABELS[m]} ({lat[m]:.2g} ms)")
        else:
            a2.axhline(summ["npib"][m], color=c, ls=":" if m == "none" else "--", lw=1, label=LABELS[m])
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

    methods = st.methods if model is not None else tuple(m for m in st.methods if m not in ("unet", "hybrid"))
    probe = replace(st, split=split, limit=n, methods=())
    base = _Runner(None, dataset, probe)
    items = base.items(range(min(n, len(base.ds))))
    if not items:
        return st, {}
    scr = torch.from_numpy(np.stack([s["screens"] for s in items]))
    psf = torch.from_numpy(np.stack([s["psf"] for s in items]))

    def npib(phi):
        with torch.no_grad():
            return float(base.pib.npib_phase(torch.as_tensor(phi), scr).mean())

    report: dict = {"split": split, "samples": len(items)}
    if "shack_hartmann" in methods:
        from .shack_hartmann import ShackHartmann

        sc = base.dev["scenario"]
        c0, a = base.dev["crop"]
        table = []
        for cfg in _grid(st.sh, SH_GRID):
            r = _Runner.__new__(_Runner)
            r.st, r.sh = st, ShackHartmann(cfg, a, c0, sc.n_grid, sc.dx, sc.receiver_aperture, sc.wavelength)
            table.append((npib(r.sh_phase(items)), cfg))
        best = max(table, key=lambda t: t[0])
        st = replace(st, sh=best[1])
        report["shack_hartmann"] = {"best": best[1].to_dict(), "npib": best[0],
                                    "table": [{**c.to_dict(), "npib": v} for v, c in table]}
        log(f"tuned Shack-Hartmann: {best[0]:.3f} with {best[1]}")
    from .retrieval import RetrievalContext, retrieve

    phi_u = None
    if model is not None and "hybrid" in methods:
        from ..reconstruction.model import load_model

        m, _ = load_model(model)
        with torch.no_grad():
            phi_u = m(psf)
    for name, grid in (("retrieval", RETRIEVAL_GRID), ("hybrid", HYBRID_GRID)):
        if name not in methods or (name == "hybrid" and phi_u is None):
            continue
        table = []
        for cfg in _grid(getattr(st, name), grid):
            ctx = RetrievalContext.build(base.dev["pupil"], base.dev["sensor"], base.dev["geometry"], cfg)
            res = retrieve(psf, ctx, cfg, init=phi_u if name == "hybrid" else None)
            table.append((npib(res["phi"]), cfg))
        best = max(table, key=lambda t: t[0])
        st = replace(st, **{name: best[1]})
        report[name] = {"best": best[1].to_dict(), "npib": best[0],
                        "table": [{**{k: getattr(c, k) for k in grid}, "npib": v} for v, c in table]}
        log(f"tuned {name}: {best[0]:.3f} with " + ", ".join(f"{k}={getattr(best[1], k)}" for k in grid))
    return st, report
