"""The pipeline's report: one self-contained HTML page (figures embedded, readable offline) with a headline
(did it pass, what it achieved), the checks with their thresholds, the provenance (what made it) and a
section per stage, each table beside its figures with a caption saying what to look at."""

from __future__ import annotations

import base64
import html
import time
from pathlib import Path

from .. import __version__
from ..tasks import file_key

__all__ = ["report_html", "provenance"]


def _table(obj, raw: tuple = ()) -> str:
    """An HTML table of rows (dicts); cells are escaped except in the ``raw`` columns (markup)."""
    rows = obj if isinstance(obj, list) else [obj]
    if not rows:
        return "<p>(empty)</p>"
    cols = list(rows[0])

    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, (list, tuple)):
            return ", ".join(fmt(x) for x in v)
        if isinstance(v, dict):
            return "; ".join(f"{k}: {fmt(x)}" for k, x in v.items())
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{r.get(c) if c in raw else fmt(r.get(c))}</td>" for c in cols) + "</tr>"
                   for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"



def _img(title: str, f: Path) -> str:
    b64 = base64.b64encode(Path(f).read_bytes()).decode()
    return f"<img alt='{html.escape(title)}' src='data:image/png;base64,{b64}'>"



def _git_commit() -> str | None:
    """The checkout's commit (None outside a git checkout, e.g. a wheel install)."""
    import subprocess

    try:
        r = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent), "rev-parse", "HEAD"],
                           capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def provenance(rec, library: Path, model: Path | None, elapsed: float, out: Path | None = None,
               layout: Path | None = None, beacon_device: Path | None = None) -> dict:
    """What the report of ``rec`` (a :class:`~.pipeline_recipe.PipelineRecipe`) is a record of: recipe,
    design, ``library`` and ``model`` (the files used), the stage-6 device (the design, sensor and layout
    the dataset was made with, ``layout``; or the ``[beacons]`` design, sensor and the design file its device
    was built from, ``beacon_device``), seeds, code, machine, date, time taken.  Each file by its sha256 and
    a path relative to the recipe's folder, or, for a product of the run, to the run folder ``out`` (where
    the report lies): the record reads the same wherever the checkout lies."""
    import os
    import platform

    base = Path(rec.source).resolve().parent
    run_dir = Path(out).resolve() if out is not None else None

    def named(p):
        if p is None:
            return None
        p = Path(p).resolve()
        in_run = run_dir is not None and p.is_relative_to(run_dir)
        return {"path": os.path.relpath(p, run_dir if in_run else base), "relative_to": "run" if in_run else "recipe",
                "sha256": file_key(p) if p.is_file() else None}

    model = model or (rec.beacons.model if rec.beacons is not None else None)
    t, b = rec.train, rec.beacons
    pv = {"recipe": {**named(rec.source), "path": Path(rec.source).name}, "design_recipe": named(rec.pipeline.design),
          "library": named(library), "sensor": named(rec.pipeline.sensor),
          "turbulence": named(rec.pipeline.turbulence),
          "model": named(model) if model is not None else None,
          "training_recipe": named(t.recipe) if t is not None and t.recipe else None,
          "dataset_seed": rec.dataset.seed if rec.dataset is not None else None}
    if rec.dataset is not None:  # stage 6 reads the dataset made on the run's own device
        pv |= {"stage6_design": named(rec.pipeline.design), "stage6_sensor": named(rec.pipeline.sensor),
               "stage6_layout": named(layout)}
    if b is not None:  # fresh beacons through a second device, designed in the run
        pv |= {"beacons_design": named(b.design), "beacons_sensor": named(b.sensor),
               "beacons_device": named(beacon_device), "beacon_seed": b.seed, "beacon_samples": b.samples}
    return pv | {"metadesign": __version__, "commit": _git_commit(), "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
                 "machine": f"{platform.node()} ({platform.system()} {platform.machine()}, {os.cpu_count()} cores, "
                            f"Python {platform.python_version()})",
                 "elapsed_seconds": round(elapsed, 1)}


#: the provenance rows' labels in the report (other keys: their name in words)
_LABELS = {"design_recipe": "design recipe (stages 2-5)", "sensor": "sensor (stage 4)",
           "stage6_design": "stage-6 device: design recipe", "stage6_sensor": "stage-6 device: sensor",
           "stage6_layout": "stage-6 device: layout the dataset was made from",
           "beacons_design": "stage-6 device (fresh beacons): design recipe",
           "beacons_sensor": "stage-6 device (fresh beacons): sensor",
           "beacons_device": "stage-6 device (fresh beacons): the design file it is built from (no layout written)",
           "beacon_seed": "fresh beacons: root seed", "beacon_samples": "fresh beacons: samples",
           "dataset_seed": "dataset: root seed"}


def _file_cell(v: dict) -> str:
    where = " (in the run folder)" if v.get("relative_to") == "run" else ""
    return f"{v['path']}{where}" + (f", sha256 {v['sha256']}" if v.get("sha256") else ", not found")


def report_html(name: str, rep: dict) -> str:
    """The report: a headline (did it pass, what it achieved) first, then a section per stage, each table
    beside its figures with a caption saying what to look at."""
    css = ("body{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222;line-height:1.4}"
           "table{border-collapse:collapse;margin:0.5em 0 1em}td,th{border:1px solid #bbb;padding:3px 8px;"
           "font-size:13px;text-align:left}th{background:#eee}img{max-width:100%;border:1px solid #ddd}"
           "h2{border-bottom:1px solid #ccc;margin-top:2em}.pass{color:#070;font-weight:bold}"
           ".fail{color:#b00;font-weight:bold}.verdict{font-size:20px;padding:0.6em 1em;border-radius:6px;"
           "display:inline-block}.ok{background:#e6f4e6}.bad{background:#fbe3e3}figcaption{font-size:13px;"
           "color:#444;margin:0.3em 0 1.2em}.small{font-size:12px;color:#555}")
    checks = rep.get("checks", [])
    passed = all(c["passed"] for c in checks)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>metadesign report: {html.escape(name)}</title>",
             f"<style>{css}</style></head><body>", f"<h1>metadesign pipeline report: {html.escape(name)}</h1>",
             f"<p class='verdict {'ok' if passed else 'bad'}'>"
             + (f"All {len(checks)} checks passed" if passed else
                f"{sum(not c['passed'] for c in checks)} of {len(checks)} checks FAILED") + "</p>"]
    hl = rep.get("headline") or {}
    if hl.get("rows"):
        parts.append(f"<h2>What it achieved</h2><p>Wavefront estimate of the {html.escape(hl['estimator'])} from the 8 "
                     "sensor spots, applied as a phase correction to a beam sent back through the same turbulence; "
                     "NPiB: the power in the target bucket over a vacuum beam's.</p>" + _table(hl["rows"]))
    parts.append("<h2>Checks</h2>" + _table([
        {"check": c["check"], "value": c["value"], "threshold": c["threshold"],
         "result": "<span class='pass'>pass</span>" if c["passed"] else "<span class='fail'>FAIL</span>",
         "why": c["why"]} for c in checks], raw=("result",)))
    pv = rep.get("provenance")
    if pv:
        rows = []
        for k, v in pv.items():
            if isinstance(v, dict):
                v = _file_cell(v)
            rows.append({"what": _LABELS.get(k, k.replace("_", " ")), "value": "-" if v is None else str(v)})
        parts.append("<h2>Provenance</h2><p class='small'>Files by their sha256; paths relative to the recipe's "
                     "folder, or to this report's for what the run made.</p>" + _table(rows))
    parts.append("<p class='small'>metadesign " + html.escape(__version__) + "; stages: " + ", ".join(
        f"{k} ({'up to date, ran in %.1f s' % v.get('ran_seconds', float('nan')) if v.get('skipped') else '%.1f s' % v['seconds']})"
        for k, v in rep["stages"].items()) + "</p>")
    for sec, body in rep.get("sections", {}).items():
        parts.append(f"<h2>{html.escape(sec)}</h2>")
        for title, rows in body["tables"]:
            parts.append(f"<h3>{html.escape(title)}</h3>{_table(rows)}")
        for title, f, caption in body["figures"]:
            if Path(f).exists():
                parts.append(f"<figure><h3>{html.escape(title)}</h3>{_img(title, f)}"
                             f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts)
