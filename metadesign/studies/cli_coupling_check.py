"""The ``library coupling-check`` and ``library coupling-sweep`` commands: a design under each device model."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..cliutil import emit, integer, limit_arg, log_to, num, out_dir, out_file, workers_arg
from ..design.store import design_file
from ..execution import scratch_path
from ..outputs import product, zarr_input
from ..validation import InputError

__all__ = ["register"]


def _cmd_coupling_check(a: argparse.Namespace) -> int:
    from ..execution import Execution
    from ..sensing.transmission import Perturbation
    from .certified import CertifiedSettings
    from .coupling_check_study import CouplingCheckRequest, run_coupling_check
    from .lpa import downstream_of

    downstream = downstream_of(a.dataset, a.model, a.samples, a.noise, a.seed, what="the NPiB")
    certified = CertifiedSettings(a.certified, a.replicates, a.peds, a.seed, a.taper_slices, a.ring, a.reoptimise,
                                  a.reoptimise_sweeps)
    pert = Perturbation.from_nm(a.bias_nm, jitter_nm=a.jitter_nm, seed=a.jitter_seed, height_nm=a.height_nm,
                                sidewall_deg=a.sidewall_deg)
    src = Path(a.design)
    req = CouplingCheckRequest(src, a.compensated, a.coupling_model, a.sensor, a.fab_library, pert, downstream,
                               certified)
    out = out_dir(a.output or (src if src.is_dir() else src.parent) / "coupling-check")
    inputs = {"design": design_file(src), "--compensated": design_file(a.compensated) if a.compensated else None,
              "--coupling-model": a.coupling_model, "--sensor": a.sensor,
              "--dataset": zarr_input(a.dataset) if a.dataset else None, "--model": a.model,
              "--peds": a.peds, "--fab-library": a.fab_library}
    with product(out, "coupling-check", inputs, scratch=(scratch_path(out),)):
        rep = run_coupling_check(req, out, Execution(workers=a.workers, scheduler=a.scheduler, log=log_to(a.json)))
    wl = max(27, *(len(c["label"]) for c in rep["cases"].values()))
    lines = [f"wrote {out}/coupling-check.json and coupling-frames.png",
             f"  {'case':<{wl}} spot eff.  spot Strehl  stray    |focal shift| um"
             + ("   U-Net NPiB" if "downstream" in rep else "")]
    for name, c in rep["cases"].items():
        mm = c["mean"]
        npib = rep.get("downstream", {}).get(name, {}).get("npib_unet")
        lines.append(f"  {c['label']:<{wl}} {mm['spot_efficiency']:.4f}     {mm['spot_strehl']:.3f}        "
                     f"{mm['stray']:.4f}   {1e3 * mm['focal_shift_mm']:7.1f}"
                     + (f"          {npib:.3f}" if npib is not None else ""))
        if "stderr" in c:
            se = c["stderr"]
            lines.append(f"  {'  +- (standard error)':<{wl}} {se['spot_efficiency']:.4f}     "
                         f"{se['spot_strehl']:.3f}        {se['stray']:.4f}   {1e3 * se['focal_shift_mm']:7.1f}"
                         f"   ({c['sampling']['supercells']} supercells of {c['sampling']['eligible_supercells']:,})"
                         + (f"   NPiB +- {rep['downstream'][name]['npib_unet_se']:.3f}"
                            if name in rep.get("downstream", {}) else ""))
        eff = ((c.get("ring") or {}).get("effect") or (c.get("reoptimise") or {}).get("effect"))
        if eff:  # a case measured on the same replicates as its plain one: the difference and its error
            lines.append(f"  {'  effect (matched replicates)':<{wl}} "
                         + ", ".join(f"{k} {v['mean'] * (1e3 if k == 'focal_shift_mm' else 1):+.4g} +- "
                                     f"{v['stderr'] * (1e3 if k == 'focal_shift_mm' else 1):.2g}"
                                     for k, v in eff.items()).replace("focal_shift_mm", "focal shift (um)"))
    if "downstream" in rep:
        d = rep["downstream"]
        lines.append(f"  NPiB uncorrected {d['npib_none']:.3f}, phase conjugate {d['npib_phase_conjugate']:.3f} "
                     f"({d['samples']} test samples, {d['noise_percent']:g} % noise)")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_coupling_sweep(a: argparse.Namespace) -> int:
    from .coupling_check import plot_sweep, sweep_axis, sweep_table

    reports, inputs = [], {}
    for i, folder in enumerate(a.reports):
        path = Path(folder) / "coupling-check.json" if Path(folder).is_dir() else Path(folder)
        try:
            rep = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"{folder}: not a coupling-check output ({exc})") from None
        if not isinstance(rep, dict) or "cases" not in rep:
            raise InputError(f"{folder}: not a coupling-check output (no cases)")
        reports.append(rep)
        inputs[f"report {i + 1}"] = path.parent if path.name == "coupling-check.json" else path  # its folder
    designs = {(r.get("design") or {}).get("sha256") for r in reports} - {None}
    if len(designs) > 1:
        raise InputError("the reports are of different designs (their design sha256 differ): one design per sweep")
    if len(reports) > 1:
        try:
            sweep_axis(reports)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    out = out_file(a.output, suffixes=(".png",))
    table = sweep_table(reports)
    with product(out, "figure", inputs):
        fig = plot_sweep(table, out)
    table["figure"] = str(fig)
    head = {"bias_nm": "  bias nm  ", "height_nm": "  etch nm  ", "sidewall_deg": "  wall deg "}[table["axis"]]
    lines = [f"wrote {fig}", head + "  ".join(f"{r['label'][:30]:>30}" for r in table["cases"].values())]
    for j, b in enumerate(table[table["axis"]]):
        cells = []
        for r in table["cases"].values():
            se = r["spot_efficiency_se"][j]
            cells.append(f"{r['spot_efficiency'][j]:.4f}" + (f" +- {se:.4f}" if se else "        "))
        lines.append(f"  {b:+7.1f}  " + "  ".join(f"{c:>30}" for c in cells))
    emit(table, a.json, "\n".join(lines + ["  (spot efficiency; the figure has Strehl, stray and focal shift)"]))
    return 0


def _add_coupling_check(sub) -> None:
    cc = sub.add_parser(
        "coupling-check", help="a design under the LPA vs the supercell coupling model (and compensated)",
        description="Channel metrics (focusing efficiency, Strehl, crosstalk, focal shift) and the 8-PSF frames "
        "of DESIGN under the LPA and under the supercell coupling model, and of --compensated (a `design "
        "compensate` output) under both; with --dataset and --model, the U-Net's NPiB on the dataset's test "
        "samples re-rendered through each. Writes OUT/coupling-check.json and figures.")
    cc.add_argument("design", help="design folder (nearest-atom)")
    cc.add_argument("--compensated", help="the compensated design folder")
    cc.add_argument("--coupling-model", help="coupling model (default: the one fitted against the library)")
    cc.add_argument("--sensor", help="sensing recipe (default: sensing/paper.toml; the dataset's with --dataset)")
    cc.add_argument("--dataset", help="dataset whose test samples are re-rendered (its device's sensor and grid)")
    cc.add_argument("--model", help="U-Net weights for the NPiB")
    limit_arg(cc, "at most this many test samples (64)", type=integer(1, 100000), default=64)
    cc.add_argument("--noise-percent", "--noise", dest="noise", type=num(0, 100, unit="%"), default=5.0,
                    help="sensor noise, %% of peak (5)")
    cc.add_argument("--certified", type=integer(0, 10_000_000), default=0, metavar="N",
                    help="also each coupled design under the certified (PEDS) model, its correction measured on N "
                    "supercells drawn at random (0.2 s each per core; resumable in OUT.partial/); 0: off (default)")
    cc.add_argument("--replicates", type=integer(3, 256), default=8,
                    help="independent replicates of the --certified sample (jackknife error bars; 8)")
    cc.add_argument("--peds", help="certified model (default: the PEDS model calibrated against the library)")
    cc.add_argument("--ring", type=integer(0, 10_000_000), default=0, metavar="N",
                    help="with --certified: also the neighbour ring on the first N of the sampled supercells, by "
                         "overlapping windows (the certified model on each one's three 2 x 2 windows straddling "
                         "towards its neighbours; 0: none)")
    cc.add_argument("--reoptimise", type=integer(0, 256), default=0, metavar="K",
                    help="with --certified, nominal widths: also each sampled supercell's atoms re-chosen under the "
                         "certified model (each position tries its atom's K nearest atoms in phase, as the "
                         "compensating discretizer does under the pair model): the device re-optimised under the "
                         "certified model, estimated from the same sample without making it (0: none)")
    cc.add_argument("--reoptimise-sweeps", type=integer(1, 8), default=1,
                    help="sweeps over the four positions of --reoptimise (1)")
    cc.add_argument("--seed", type=integer(0, 2**63 - 1), default=0, help="seed of the --certified sample (0)")
    cc.add_argument("--bias-nm", type=num(-50, 50, unit="nm"), default=0.0,
                    help="every device made with this width bias (nm; a fab study under each model; 0)")
    cc.add_argument("--jitter-nm", type=num(0, 20, unit="nm"), default=0.0,
                    help="every device made with this random width error per pillar (nm, sigma; 0)")
    cc.add_argument("--jitter-seed", type=integer(0, 2**63 - 1), default=0, help="seed of the jitter (0)")
    cc.add_argument("--height-nm", type=num(-100, 100, unit="nm"), default=0.0,
                    help="every device made with this etch-depth error (pillar height - nominal, nm; needs "
                    "--fab-library; the certified model solves at that height; 0)")
    cc.add_argument("--sidewall-deg", type=num(60, 90, unit="deg"), default=90.0,
                    help="every device made with this wall angle (90 = vertical; needs --fab-library; the certified "
                    "model's low fidelity tapers its pillars in --taper-slices slices; 90)")
    cc.add_argument("--taper-slices", type=integer(0, 64), default=4,
                    help="slices of the certified model's tapered supercells with --sidewall-deg (0: vertical at "
                    "mid-height widths; 4)")
    cc.add_argument("--fab-library", help="library with height / sidewall axes for --height-nm / --sidewall-deg "
                    "(e.g. library/paper-fab.npz)")
    cc.add_argument("--scheduler", help="Dask scheduler address for the certified solves (default: the local pool)")
    workers_arg(cc)
    cc.add_argument("-o", "--output", help="output folder (default: coupling-check/ beside the design)")
    cc.add_argument("--json", action="store_true", help="print the report as JSON")
    cc.set_defaults(func=_cmd_coupling_check)


def _add_coupling_sweep(sub) -> None:
    sw = sub.add_parser(
        "coupling-sweep", help="fab-tolerance curves from coupling-check reports at several width biases or etch "
        "depths",
        description="Reads coupling-check outputs of one design (the same --seed, so the certified points "
        "share their sample) made with different --bias-nm (or different --height-nm) and draws spot "
        "efficiency, Strehl, stray light and focal shift against that perturbation under each device model (LPA, "
        "coupling model, certified with its error bars); reports of different designs, or differing in both, "
        "are refused. Writes OUT (.png).")
    sw.add_argument("reports", nargs="+", help="coupling-check output folders (or their coupling-check.json)")
    sw.add_argument("-o", "--output", required=True, help="figure (.png)")
    sw.add_argument("--json", action="store_true", help="print the table as JSON")
    sw.set_defaults(func=_cmd_coupling_sweep)


def register(sub, groups: dict) -> None:
    """Add ``coupling-check`` and ``coupling-sweep`` to the ``library`` group."""
    _add_coupling_check(groups["library"])
    _add_coupling_sweep(groups["library"])
