"""What the supercell coupling does to a device, and what the compensating discretizer gives back.

Four devices on the same sensor: the design under the LPA (what every earlier figure assumed), the same
design under the coupling model (what the fab would make, as far as the model knows), and the compensated
design (:mod:`metadesign.design.compensate`) under the coupling model (and under the LPA, for reference).
Per channel, on the total field as the camera sees it (:func:`metadesign.sensing.model.spot_metrics`: under
coupling a pillar's light is not its own, so the sub-lattice metrics of the LPA studies are kept only as a
second column): spot efficiency, spot Strehl, stray light in the quadrant, focal shift; the 8-PSF frames side by side; with a
dataset and a U-Net, the U-Net's NPiB on its test samples re-rendered through each device."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..design.compensate import atom_neighbours, descend_under, sampled_supercells
from ..library.coupling import relative_error
from ..library.coupling_net import coupling_t
from ..library.peds import PedsModel, certified_t, find_peds, load_peds, neighbour_windows, window_ring
from ..plotting import pyplot, save_figure
from ..sensing.forward import sensor_frames
from ..sensing.model import channel_metrics, spot_metrics
from ..sensing.plot import case_label
from ..sensing.sampled import (
    delta_pupil,
    eligible_supercells,
    jackknife_bias,
    jackknife_se,
    sampled_spot_metrics,
    supercell_widths,
)
from ..sensing.sensor import SensorSpec
from ..sensing.transmission import Perturbation, couple_supercells, unit_t_as_made
from .lpa import pupil_downstream

__all__ = ["CASES", "SPOT_KEYS", "SWEEP_AXES", "certified_case", "coupling_check", "plot_case_metrics",
           "plot_coupling_frames", "sweep_axis", "sweep_table", "plot_sweep"]

SPOT_KEYS = ("spot_efficiency", "spot_strehl", "stray", "focal_shift_mm")
SPOT_TITLES = dict(zip(SPOT_KEYS, ("spot efficiency", "spot Strehl", "stray fraction", "|focal shift| (um)")))

CASES = {"lpa": "design, LPA", "coupled": "design, supercell coupling", "compensated": "compensated, coupling",
         "compensated_lpa": "compensated, LPA", "certified": "design, certified (PEDS, sampled)",
         "compensated_certified": "compensated, certified (PEDS, sampled)",
         "certified_ring": "design, certified (PEDS, overlapping windows, sampled)",
         "compensated_certified_ring": "compensated, certified (PEDS, overlapping windows, sampled)",
         "certified_reoptimised": "design, atoms re-chosen under the certified model (sampled)",
         "compensated_certified_reoptimised": "compensated, atoms re-chosen under the certified model (sampled)"}


def _mean(rows, key):
    return float(np.mean([abs(r[key]) if key == "focal_shift_mm" else r[key] for r in rows]))


def coupling_check(fabs: dict, sensor: SensorSpec, grid: int, dataset=None, model=None, samples: int = 64,
                   noise_percent: float = 5.0, seed: int = 0, log=lambda s: None,
                   certified: dict | None = None, pert: Perturbation = Perturbation(),
                   designs: dict | None = None) -> tuple[dict, dict]:
    """``fabs``: case name -> :class:`~metadesign.sensing.model.AsFabricated` (its coupling set).  Returns
    the report and the flat-wavefront frames per case.  ``certified``: ``{"supercells": n, "replicates": R,
    "partial": folder, "peds": model or None, "workers": j, "scheduler": address or None, "seed": s,
    "taper_slices": k}``: each
    coupled case (``coupled``, ``compensated``) also under the certified model, sampled
    (:func:`certified_case`; no flat-wavefront frames; with a dataset and a model, the NPiB from the
    sampled device's frames, with its jackknife error bar).  ``pert``: every
    device made with those widths (bias, jitter: the same pillars in every case and in the sample) and that
    global etch-depth error and wall angle (the devices' ``fab_lib`` gives the unit cells' change with height
    and angle; the certified model solves its supercells at that height, tapered in ``taper_slices`` slices
    of the ``certified`` dict, or vertical at mid-height widths with 0).  ``certified["reoptimise"] = (K,
    sweeps)`` with ``designs`` (case name -> its :class:`~metadesign.design.store.Design`): each certified case
    also with its sampled supercells' atoms re-chosen under the certified model (``reoptimise`` of
    :func:`certified_case`)."""
    if pert.height_gradient or pert.sidewall_gradient_deg:
        raise ValueError("coupling_check: width errors and a global etch depth and wall angle only (no gradients "
                         "across the device)")
    pupils, frames = {}, {}
    rep = {"cases": {}, "sensor_distance_m": sensor.distance, "bias_nm": [pert.bias_x * 1e9, pert.bias_y * 1e9],
           "jitter_nm": pert.jitter * 1e9, "jitter_seed": pert.seed, "corner_nm": pert.corner_radius * 1e9,
           "height_nm": round(pert.height * 1e9, 6), "sidewall_deg": pert.sidewall_deg}
    for name, fab in fabs.items():
        t0 = time.perf_counter()
        log(f"  {CASES.get(name, name)}: pupil ...")
        cp = fab.pupil(sensor.distance, grid, pert)
        pupils[name] = cp
        frames[name] = sensor_frames(cp, sensor)
        m = spot_metrics(cp, sensor, fab)
        sl = channel_metrics(cp, sensor, fab)
        rep["cases"][name] = {
            "label": CASES.get(name, name), "coupling": fab.coupling_name, "seconds": time.perf_counter() - t0,
            "channels": m, "mean": {k: _mean(m, k) for k in SPOT_KEYS},
            "sublattice_mean": {k: _mean(sl, k) for k in ("focusing_efficiency", "strehl", "crosstalk")},
            "power_on_sensor": [float(f.sum()) / (fab.n_cells * fab.period) ** 2 for f in frames[name]],
        }
    sampled = {}
    if certified and certified.get("reoptimise") and not all(n in (designs or {}) for n in ("coupled", "compensated")
                                                             if n in fabs):
        raise ValueError("coupling_check: re-optimising needs each coupled case's design (designs=)")
    if certified:
        for name, cert in (("coupled", "certified"), ("compensated", "compensated_certified")):
            if name in fabs:
                log(f"  {CASES[cert]}: {certified['supercells']} supercells through the certified model ...")
                reo = certified.get("reoptimise")
                rep["cases"][cert], deltas, ring = certified_case(
                    fabs[name], pupils[name], sensor, grid, label=CASES[cert], log=log, pert=pert,
                    partial=f"{certified['partial']}/{name}", return_deltas=True,
                    reoptimise=(designs[name], *reo) if reo else None,
                    **{k: v for k, v in certified.items() if k not in ("partial", "reoptimise")})
                if reo:
                    rep["cases"][cert + "_reoptimised"] = {**rep["cases"][cert].pop("reoptimised"),
                                                           "label": CASES[cert + "_reoptimised"]}
                sampled[cert] = (name, deltas)
                if ring is not None:
                    rep["cases"][cert + "_ring"] = rep["cases"][cert].pop("with_ring")
                    sampled[cert + "_ring"] = (name, ring)
    base = rep["cases"].get("lpa", {}).get("mean")
    if base:
        for c in rep["cases"].values():
            c["relative_to_lpa"] = {k: (c["mean"][k] / base[k] if base[k] else None)
                                    for k in ("spot_efficiency", "spot_strehl", "stray")}
    if dataset is not None and model is not None:
        any_fab = next(iter(fabs.values()))
        rep["downstream"] = pupil_downstream(pupils, dataset, model, any_fab, samples, noise_percent, seed, log,
                                             sampled=sampled)
    return rep, frames


def certified_case(fab, cp, sensor: SensorSpec, grid: int, supercells: int = 2000, replicates: int = 8,
                   partial=None, peds=None, workers: int = 1, scheduler: str | None = None, seed: int = 0,
                   label: str = CASES["certified"], pert: Perturbation = Perturbation(),
                   log=lambda s: None, return_deltas: bool = False, taper_slices: int = 4,
                   ring_supercells: int = 0, reoptimise: tuple | None = None):
    """``fab`` (with its supercell coupling model) under the certified model: its coupled pupil ``cp`` plus
    the certified model's correction ``t_peds - t_coupled``, measured on ``supercells`` supercells drawn
    uniformly (seeded) from the device's complete ones in ``replicates`` equal replicates
    (:mod:`metadesign.sensing.sampled`), with the widths, etch depth and wall angle of ``pert`` (``cp`` made
    with it, on ``grid``; the pillars' unit cells as the device's, the low-fidelity solves at the etched
    height, with sloped walls in ``taper_slices`` slices (0: vertical, the widths at mid-height)).  The case's
    metrics, their jackknife standard errors, and the corrections' statistics (in units of the pillars'
    rms |t|, as the certification); with ``return_deltas``, also the replicates' correction pupils
    (``(report, deltas, deltas with the ring or None)``: the sampled device's frames,
    :func:`~metadesign.sensing.sampled.sampled_frames`).

    ``ring_supercells``: also the neighbour ring, by overlapping windows
    (:func:`~metadesign.library.peds.window_ring`): each of the first ``ring_supercells / replicates``
    supercells of every replicate gets its ring term from the certified model on its three windows that
    straddle towards +x, +y and +x+y (with its neighbours as made; solved like the supercells: at the etched
    height, tapered), weighted for its sub-sample, so a replicate still estimates the whole correction
    without bias; supercells whose windows leave the device's complete supercells (the aperture's rim) get
    none.  The report's ``with_ring`` is then the same replicates with the ring added (its effect on a
    matched sample, with its jackknife standard error in ``with_ring["ring"]["effect"]``).

    ``reoptimise = (design, K, sweeps)`` (``design`` the device's own, nominal widths only): the sampled
    supercells' atoms re-chosen under the certified model, as the compensating discretizer chooses them
    under the pair model (:func:`~metadesign.design.compensate.descend_under`: each position tries its
    atom's ``K`` nearest atoms in phase, ``sweeps`` times, towards ``gamma_p mean_i exp(i phi_i,p)``, with
    ``gamma_p`` fitted to the sample's starting atoms under the certified model).  Given ``gamma``, a
    supercell's choice depends only on its own atoms and target, so the sample's re-chosen supercells are
    those of the device re-optimised whole, and the same replicates estimate that device (each pillar's
    correction: from its coupled ``t`` among the starting atoms to its coupled ``t`` among the new ones, plus
    the supercell's certified correction; on the coupled pupil ``cp`` of the starting design) without
    making it.  ``gamma``'s own sampling error (O(1/n)) is not in the error bars.  The report's
    ``reoptimised`` (its effect against the starting design on matched replicates in
    ``reoptimised["reoptimise"]["effect"]``)."""
    t0 = time.perf_counter()
    if fab.coupling is None:
        raise ValueError("certified_case: the device needs its coupling model (the control variate)")
    if reoptimise is not None and replace(pert, seed=0) != Perturbation():
        raise ValueError("certified_case: re-optimising the atoms is for the nominal device (no width, etch or wall "
                         "error)")
    pm = peds if isinstance(peds, PedsModel) else load_peds(peds if peds is not None else find_peds(fab.lib), fab.lib)
    ids = eligible_supercells(fab)
    m = supercells // replicates
    if m < 1 or replicates < 3:
        raise ValueError("certified_case: at least three replicates of one supercell each")
    pick = ids[np.random.default_rng(seed).integers(0, len(ids), m * replicates)]
    w = supercell_widths(fab, pick, replace(pert, height=0.0, sidewall_deg=90.0), grid)  # widths at mid-height
    tu = unit_t_as_made(fab.lib, w[..., 0], w[..., 1], pert, fab.fab_lib)
    t_pair = coupling_t(fab.coupling, w, tu)
    stack = replace(fab.lib.stack, height=fab.lib.stack.height + pert.height)
    def progress_lines(what, steps=""):
        said = {"pass": 0, "last": -1, "tenths": set()}

        def progress(d, n):  # a line per tenth of each pass (one pass per low-fidelity level)
            if d < said["last"]:
                said["pass"], said["tenths"] = said["pass"] + 1, set()
            said["last"] = d
            if d * 10 // max(n, 1) not in said["tenths"]:
                said["tenths"].add(d * 10 // max(n, 1))
                k, L = said["pass"], len(pm.harmonics)
                where = f"level {k + 1}" if not steps else f"{steps} {k // L + 1}, level {k % L + 1}"
                log(f"    {what}, {where}: {d}/{n} ({time.perf_counter() - t0:.0f} s)")
        return progress

    taper = (pert.sidewall_deg, taper_slices) if pert.sidewall_deg != 90.0 and taper_slices else None
    t_cert = certified_t(fab.lib, w, partial, pm, workers=workers, scheduler=scheduler,
                         progress=progress_lines("certified solves"),
                         stack=stack, t_unit=tu, taper=taper)
    delta = (t_cert - t_pair).astype(np.complex64)
    ring_rep, ring_rows = None, [np.zeros(0, np.int64)] * replicates
    if ring_supercells:
        k = min(m, ring_supercells // replicates)
        if k < 1:
            raise ValueError("certified_case: at least one ring supercell per replicate")
        sub = np.concatenate([np.arange(r * m, r * m + k) for r in range(replicates)])
        C2 = fab.n_cells // 2
        s_ids = pick[sub]
        corners = [s_ids + 1, s_ids + C2, s_ids + C2 + 1]  # the neighbours at +x, +y, +x+y
        whole = (s_ids % C2 + 1 < C2) & np.all([np.isin(c, ids) for c in corners], axis=0)
        nw = int(whole.sum())  # the three neighbours' widths in one pass over the device's rows
        wn = supercell_widths(fab, np.concatenate([c[whole] for c in corners]),
                              replace(pert, height=0.0, sidewall_deg=90.0), grid)
        wq = [w[sub][whole]] + [wn[i * nw:(i + 1) * nw] for i in range(3)]
        nbhd = np.concatenate([np.concatenate([wq[0], wq[1]], 2), np.concatenate([wq[2], wq[3]], 2)], 1)[:, :3, :3]
        win = neighbour_windows(nbhd).reshape(-1, 2, 2, 2)
        log(f"    neighbour ring: {len(win)} straddling windows of {int(whole.sum())} supercells ...")
        t_r = time.perf_counter()
        tu_w = unit_t_as_made(fab.lib, win[..., 0], win[..., 1], pert, fab.fab_lib)
        t_win = certified_t(fab.lib, win, f"{partial}/ring", pm, workers=workers, scheduler=scheduler,
                            progress=progress_lines("ring windows"), stack=stack, t_unit=tu_w,
                            taper=taper).reshape(-1, 3, 2)
        rterm = np.zeros((len(sub), 2), np.complex128)
        rterm[whole] = window_ring(t_win, t_cert[sub][whole])
        ring_rows = [np.arange(r * k, (r + 1) * k) for r in range(replicates)]
        rel_r = np.abs(rterm) / np.sqrt((np.abs(tu[sub]) ** 2).mean((1, 2)))
        ring_rep = {"supercells": int(len(sub)), "with_neighbours": int(whole.sum()), "windows": int(len(win)),
                    "seconds": time.perf_counter() - t_r, "mean_relative": [float(v) for v in rel_r.mean(0)],
                    "p90_relative": [float(v) for v in np.percentile(rel_r, 90, axis=0)],
                    "mean_complex": [[float(v.real), float(v.imag)] for v in rterm.mean(0)]}
        ring_ids, ring_delta, ring_weight = s_ids, rterm.astype(np.complex64), len(ids) / k
    t_solved = time.perf_counter()
    plain = [delta_pupil(fab, cp.z, grid, pick[r * m:(r + 1) * m], delta[r * m:(r + 1) * m], len(ids) / m)
             for r in range(replicates)]
    deltas = plain
    if ring_rep is not None:  # the ring's sub-sample, weighted for its own size, on top of the same replicates
        deltas = [_plus_pupil(d, delta_pupil(fab, cp.z, grid, ring_ids[ring_rows[r]], ring_delta[ring_rows[r]],
                                             ring_weight)) for r, d in enumerate(plain)]
    rel = relative_error(t_cert, t_pair, tu)  # the certification's measure: in units of the pillars' rms |t|
    rep = {
        "label": label,
        "coupling": "certified (PEDS), sampled", "seconds": time.perf_counter() - t0,
        "seconds_solves": t_solved - t0, **_sampled_metrics(cp, plain, sensor, fab),
        "sampling": {"supercells": int(m * replicates), "replicates": int(replicates), "seed": int(seed),
                     "eligible_supercells": len(ids), "distinct_sampled": len(np.unique(pick))},
        "peds": {"harmonics": list(pm.harmonics), "library_sha256": pm.library_sha256,
                 "taper": list(taper) if taper else None,
                 "coefficients": [[float(c.real), float(c.imag)] for c in np.atleast_1d(pm.coef)]},
        "ring": None,
        "correction": {"mean_relative": [float(v) for v in rel.mean(0)],
                       "p90_relative": [float(v) for v in np.percentile(rel, 90, axis=0)],
                       "mean_complex": [[float(v.real), float(v.imag)] for v in delta.mean(0)]},
    }
    if ring_rep is not None:  # the same sample with the ring added: the ring's effect on matched replicates
        ring_case = _sampled_metrics(cp, deltas, sensor, fab)
        a, b = ring_case.pop("_loo"), rep["_loo"]
        ring_rep["effect"] = {k: {"mean": ring_case["mean"][k] - rep["mean"][k],
                                  "stderr": jackknife_se(np.subtract(a[k], b[k]))} for k in SPOT_KEYS}
        rep["with_ring"] = {**{k: v for k, v in rep.items() if k not in ("with_ring", "_loo")},
                            "label": label.replace("(PEDS", "(PEDS, overlapping windows"),
                            "coupling": "certified (PEDS on overlapping windows), sampled", "ring": ring_rep,
                            "seconds": time.perf_counter() - t0, **ring_case}
    if reoptimise is not None:  # the same replicates with the re-chosen atoms: their effect on a matched sample
        reo_rep, D = _reoptimise_sample(reoptimise, fab, pick, w, t_cert, pm, f"{partial}/reoptimise",
                                        workers, scheduler, progress_lines("re-optimising", "step"), log)
        reo = [delta_pupil(fab, cp.z, grid, pick[r * m:(r + 1) * m], D[r * m:(r + 1) * m], len(ids) / m)
               for r in range(replicates)]
        reo_case = _sampled_metrics(cp, reo, sensor, fab)
        a, b = reo_case.pop("_loo"), rep["_loo"]
        reo_rep["effect"] = {k: {"mean": reo_case["mean"][k] - rep["mean"][k],
                                 "stderr": jackknife_se(np.subtract(a[k], b[k]))} for k in SPOT_KEYS}
        rep["reoptimised"] = {**{k: v for k, v in rep.items() if k not in ("with_ring", "_loo", "correction", "ring")},
                              "label": f"{label}, atoms re-chosen under it",
                              "coupling": "certified (PEDS), sampled; atoms re-chosen under it",
                              "reoptimise": reo_rep, "seconds": time.perf_counter() - t0, **reo_case}
    rep.pop("_loo")
    return (rep, plain, deltas if ring_rep is not None else None) if return_deltas else rep


def _pillar_t(fab, w: np.ndarray) -> np.ndarray:
    """(n, 2, 2, 2 pol) each pillar's ``t`` under the device's coupling model (its unit cell plus its coupling
    term, as the coupled pupil has it) for nominal supercells ``w`` (n, 2, 2, 2) m: the supercells side by
    side in one strip of two rows."""
    n = len(w)
    tu = unit_t_as_made(fab.lib, w[..., 0], w[..., 1], Perturbation(), fab.fab_lib)
    strip = lambda x: np.swapaxes(x, 0, 1).reshape(2, 2 * n, *x.shape[3:])  # noqa: E731  [s, r, c] -> [r, 2s + c]
    t = couple_supercells(strip(tu).astype(np.complex64), strip(w), np.ones((2, 2 * n), bool), fab.coupling)
    return np.swapaxes(np.asarray(t).reshape(2, n, 2, 2), 0, 1)


def _reoptimise_sample(reoptimise, fab, pick, w, t_cert, pm, partial, workers, scheduler, progress, log):
    """The sampled supercells' atoms re-chosen under the certified model (``reoptimise`` of
    :func:`certified_case`): ``(report, per-pillar correction (n, 2, 2, 2) to the coupled pupil)``: each
    pillar moves from its coupled ``t`` among the starting atoms to its coupled ``t`` among the new ones, and
    the supercell's mean from there to the certified model's ``t`` of the new atoms."""
    design, K, sweeps = reoptimise
    t0 = time.perf_counter()
    a, S = sampled_supercells(design, pick)
    aw = np.stack([design.atoms.wx, design.atoms.wy], 1)
    if a.min() < 0 or a.max() >= len(aw) or not np.allclose(aw[a], w, rtol=0, atol=1e-12):
        raise ValueError("certified_case: the design to re-optimise is not the device's (its atoms' widths differ)")
    gamma = (np.conj(S) * t_cert).sum(0) / (np.abs(S) ** 2).sum(0)
    target = S * gamma
    nbr = atom_neighbours(design.atoms.phase, min(int(K), len(aw)))
    solved = [0]

    def evaluate(tuples):
        solved[0] += len(tuples)
        return certified_t(fab.lib, aw[tuples], partial, pm, workers=workers, scheduler=scheduler, progress=progress)

    log(f"    re-optimising {len(a)} supercells under the certified model: {nbr.shape[1]} candidates per position, "
        f"{sweeps} sweep(s), {len(a) * 4 * sweeps * (nbr.shape[1] - 1)} solves ...")
    a_new = a.copy()
    t_new = descend_under(a_new, target, nbr, evaluate, sweeps, t=t_cert)
    c0, c1 = (np.abs(t_cert - target) ** 2).mean(0), (np.abs(t_new - target) ** 2).mean(0)
    p_old, p_new = _pillar_t(fab, aw[a]), _pillar_t(fab, aw[a_new])
    D = p_new - p_old + (t_new - p_new.mean((1, 2)))[:, None, None, :]
    return {"neighbours": int(nbr.shape[1]), "sweeps": int(sweeps), "supercells": int(len(a)),
            "gamma": [[float(g.real), float(g.imag)] for g in gamma],
            "residual_rms_before": np.sqrt(c0).tolist(), "residual_rms_after": np.sqrt(c1).tolist(),
            "pillars_changed_fraction": float((a_new != a).mean()), "solves": int(solved[0]),
            "seconds": time.perf_counter() - t0,
            "cost": "sum_p |t_certified,p - gamma_p mean_i exp(i phi_i,p)|^2 per supercell"}, D.astype(np.complex64)


def _plus_pupil(a, b):
    """Two coarse pupils of the same grid, summed."""
    return replace(a, G=a.G + b.G)


def _sampled_metrics(cp, deltas, sensor, fab) -> dict:
    """The spot metrics of ``cp`` plus the sampled replicate corrections ``deltas``, per channel with their
    jackknife errors, their means, standard errors and jackknife bias estimates."""
    rows, loo = sampled_spot_metrics(cp, deltas, sensor, fab)
    for i, row in enumerate(rows):
        for k in SPOT_KEYS:
            row[k + "_se"] = jackknife_se([lo[i][k] for lo in loo])
    means = {k: [_mean(lo, k) for lo in loo] for k in SPOT_KEYS}
    return {"channels": rows, "mean": {k: _mean(rows, k) for k in SPOT_KEYS}, "_loo": means,
            "stderr": {k: jackknife_se(means[k]) for k in SPOT_KEYS},
            # the jackknife's estimate of the sampling bias (the peaks behind the Strehl and the focus are
            # maxima over noisy points: biased up by O(1 / supercells)); small beside stderr when it suffices
            "bias": {k: jackknife_bias(_mean(rows, k), [_mean(lo, k) for lo in loo]) for k in SPOT_KEYS}}


def plot_case_metrics(rep: dict, out):
    """The mean spot metrics of every case side by side, sampled (certified) cases with their standard
    errors (2 sigma bars): what the certified model changes, and how sure the sampling is of it."""
    plt = pyplot()
    names = list(rep["cases"])
    fig, axs = plt.subplots(1, 4, figsize=(15, 3.6), constrained_layout=True)
    colours = {"lpa": "0.6", "compensated_lpa": "0.8", "coupled": "C0", "compensated": "C2", "certified": "C1",
               "compensated_certified": "C3", "certified_ring": "C4", "compensated_certified_ring": "C5",
               "certified_reoptimised": "C6", "compensated_certified_reoptimised": "C7"}
    for ax, (k, title) in zip(axs, SPOT_TITLES.items()):
        scale = 1e3 if k == "focal_shift_mm" else 1.0
        for i, n in enumerate(names):
            c = rep["cases"][n]
            se = c.get("stderr", {}).get(k, 0.0)
            ax.errorbar(i, c["mean"][k] * scale, yerr=2 * se * scale if se else None, fmt="o", ms=7, capsize=4,
                        color=colours.get(n, f"C{i}"))
        ax.axhline(rep["cases"][names[0]]["mean"][k] * scale, color="0.6", lw=0.8, ls=":")
        ax.set_xticks(range(len(names)), [c["label"] for c in rep["cases"].values()], rotation=35, ha="right",
                      fontsize=7)
        ax.set_xlim(-0.6, len(names) - 0.4)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"Spot metrics per device model, {case_label(rep)} device (mean of 8 channels; sampled cases: "
                 "+-2 standard errors)", fontsize=10)
    return save_figure(fig, out)


def plot_coupling_frames(frames: dict, sensor: SensorSpec, out, labels=CASES):
    """The 8-PSF frames (x-pol top, y-pol bottom) of each case side by side, each quadrant scaled to the
    brightest quadrant of the LPA frame of its polarisation, so a dimmer or spread spot reads as such."""
    plt = pyplot()
    names = list(frames)
    fig, axs = plt.subplots(2, len(names), figsize=(3.6 * len(names), 5.6), constrained_layout=True, squeeze=False)
    X, Y = sensor.coords()
    ext = np.array([X.min(), X.max(), Y.min(), Y.max()]) * 1e6
    for p in range(2):
        ref = frames[names[0]][p].max()
        for j, n in enumerate(names):
            ax = axs[p, j]
            ax.imshow(np.sqrt(frames[n][p] / ref), origin="lower", extent=ext, cmap="inferno", vmin=0, vmax=1)
            ax.set_title(f"{labels.get(n, n)}\n{'xy'[p]}-pol, peak {frames[n][p].max() / ref:.2f}", fontsize=9)
            ax.set_xlabel("x in the focal plane (um)", fontsize=8)
            if j == 0:
                ax.set_ylabel("y (um)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.suptitle("8-PSF frames (sqrt of intensity, relative to the LPA design's peak)", fontsize=10)
    return save_figure(fig, out)


SWEEP_AXES = {"bias_nm": "width bias (nm)", "height_nm": "etch depth error (nm)",
              "sidewall_deg": "sidewall angle (deg)"}


def _bias(r: dict) -> float:
    return (r.get("bias_nm") or [0.0])[0]


def _axis_values(reports: list[dict]) -> dict:
    return {"bias_nm": [_bias(r) for r in reports], "height_nm": [r.get("height_nm", 0.0) for r in reports],
            "sidewall_deg": [r.get("sidewall_deg", 90.0) for r in reports]}


def sweep_axis(reports: list[dict]) -> str:
    """The one perturbation that varies across coupling-check reports (a key of :data:`SWEEP_AXES`: width
    bias, etch depth or sidewall angle); ValueError when several vary, or none does (a repeated device)."""
    values = _axis_values(reports)
    varying = [k for k, v in values.items() if len(set(v)) > 1]
    if len(varying) > 1:
        raise ValueError(f"the reports differ in {' and '.join(SWEEP_AXES[k].split(' (')[0] for k in varying)}: "
                         "one perturbation per sweep")
    if not varying:
        raise ValueError(f"the reports repeat one device (width bias {values['bias_nm'][0]:g} nm, etch depth "
                         f"{values['height_nm'][0]:g} nm, wall {values['sidewall_deg'][0]:g} deg): one report "
                         "per value")
    v = values[varying[0]]
    if len(set(v)) != len(v):
        raise ValueError(f"the reports' {SWEEP_AXES[varying[0]].split(' (')[0]}s repeat "
                         f"({', '.join(f'{x:g}' for x in v)}): one report per value")
    return varying[0]


def sweep_table(reports: list[dict]) -> dict:
    """Coupling-check reports of one design made with different width biases (or etch depths, or wall
    angles: :func:`sweep_axis`) -> per case, per metric, the values (and standard errors) in order of that
    axis: ``{"axis": "bias_nm", "bias_nm": [...], "height_nm": [...], "sidewall_deg": [...], "cases": {name:
    {"label", key: [...], key + "_se": [...]}}}`` (cases present in every report)."""
    axis = sweep_axis(reports) if len(reports) > 1 else "bias_nm"
    order = np.argsort(_axis_values(reports)[axis], kind="stable")
    reps = [reports[i] for i in order]
    names = [n for n in reps[0]["cases"] if all(n in r["cases"] for r in reps)]
    out = {"axis": axis, **_axis_values(reps), "jitter_nm": [r.get("jitter_nm", 0.0) for r in reps], "cases": {}}
    for n in names:
        row = {"label": reps[0]["cases"][n]["label"]}
        for k in SPOT_KEYS:
            row[k] = [r["cases"][n]["mean"][k] for r in reps]
            row[k + "_se"] = [r["cases"][n].get("stderr", {}).get(k, 0.0) for r in reps]
        out["cases"][n] = row
    return out


def plot_sweep(table: dict, out):
    """Spot efficiency, Strehl, stray light and |focal shift| against the width bias (or the etch depth: the
    table's ``axis``), one line per device model; the sampled (certified) ones with +-2 standard-error bars:
    a fab-tolerance curve per model."""
    plt = pyplot()
    fig, axs = plt.subplots(1, 4, figsize=(15, 3.6), constrained_layout=True)
    axis = table.get("axis", "bias_nm")
    b = np.asarray(table[axis])
    styles = {"lpa": dict(color="0.5", ls="--", marker="s"), "coupled": dict(color="C0", marker="o"),
              "certified": dict(color="C1", marker="D", lw=2)}
    for ax, (k, title) in zip(axs, SPOT_TITLES.items()):
        scale = 1e3 if k == "focal_shift_mm" else 1.0
        for i, (n, row) in enumerate(table["cases"].items()):
            v = np.abs(row[k]) * scale if k == "focal_shift_mm" else np.asarray(row[k])
            se = np.asarray(row[k + "_se"]) * scale
            ax.errorbar(b, v, yerr=2 * se if se.any() else None, capsize=3, label=row["label"],
                        **styles.get(n, dict(color=f"C{i + 2}", marker="^")))
        ax.set_xlabel(SWEEP_AXES[axis], fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize=7)
    fig.suptitle("Fab tolerance of the spots under each device model (mean of 8 channels; sampled: +-2 standard "
                 "errors)", fontsize=10)
    return save_figure(fig, out)
