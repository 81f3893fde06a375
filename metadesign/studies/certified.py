"""A device under the certified (PEDS) supercell model, known by sampling (:func:`certified_case`): the
coupled pupil plus the certified model's correction measured on a seeded sample of the device's supercells,
in replicates (jackknife error bars); optionally the neighbour ring by overlapping windows and the sampled
supercells' atoms re-chosen under the certified model, each on the same replicates (their effect on a
matched sample).  :mod:`metadesign.studies.coupling_check` runs it for each coupled case."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..design.compensate import atom_neighbours, descend_under, sampled_supercells
from ..execution import SERIAL, Execution
from ..library.coupling import relative_error
from ..library.coupling_net import coupling_t
from ..library.peds import PedsModel, certified_t, find_peds, load_peds, neighbour_windows, window_ring
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

__all__ = ["CertifiedSettings", "SampledDevice", "certified_case", "SPOT_KEYS", "CERTIFIED_LABEL"]

SPOT_KEYS = ("spot_efficiency", "spot_strehl", "stray", "focal_shift_mm")

#: the certified case's label (:data:`metadesign.studies.coupling_check.CASES`)
CERTIFIED_LABEL = "design, certified (PEDS, sampled)"


@dataclass(frozen=True)
class CertifiedSettings:
    """How a certified case is measured (:func:`certified_case`): ``supercells`` drawn with ``seed`` in
    ``replicates`` replicates through ``peds`` (a :class:`~metadesign.library.peds.PedsModel`, its file, or
    None: the one calibrated against the library), tapered in ``taper_slices`` slices under a sloped wall;
    ``ring_supercells``: also the neighbour ring on that many of them (0: none); ``reoptimise``: also the
    sampled supercells' atoms re-chosen among each atom's K nearest (0: none), ``reoptimise_sweeps`` times.

    ``ring_supercells``: also the neighbour ring, by overlapping windows
    (:func:`~metadesign.library.peds.window_ring`): each of the first ``ring_supercells / replicates``
    supercells of every replicate gets its ring term from the certified model on its three windows that
    straddle towards +x, +y and +x+y (with its neighbours as made; solved like the supercells: at the etched
    height, tapered), weighted for its sub-sample, so a replicate still estimates the whole correction
    without bias; supercells whose windows leave the device's complete supercells (the aperture's rim) get
    none.  The report's ``with_ring`` is then the same replicates with the ring added (its effect on a
    matched sample, with its jackknife standard error in ``with_ring["ring"]["effect"]``).

    ``reoptimise = K`` (``device.design`` the device's own, nominal widths only): the sampled
    supercells' atoms re-chosen under the certified model, as the compensating discretizer chooses them
    under the pair model (:func:`~metadesign.design.compensate.descend_under`: each position tries its
    atom's ``K`` nearest atoms in phase, ``reoptimise_sweeps`` times, towards ``gamma_p mean_i exp(i
    phi_i,p)``, with ``gamma_p`` fitted to the sample's starting atoms under the certified model).  Given
    ``gamma``, a supercell's choice depends only on its own atoms and target, so the sample's re-chosen
    supercells are those of the device re-optimised whole, and the same replicates estimate that device (each
    pillar's correction: from its coupled ``t`` among the starting atoms to its coupled ``t`` among the new
    ones, plus the supercell's certified correction; on the coupled pupil ``cp`` of the starting design)
    without making it.  ``gamma``'s own sampling error (O(1/n)) is not in the error bars.  The report's
    ``reoptimised`` (its effect against the starting design on matched replicates in
    ``reoptimised["reoptimise"]["effect"]``).
    """

    supercells: int = 2000
    replicates: int = 8
    peds: Any = None
    seed: int = 0
    taper_slices: int = 4
    ring_supercells: int = 0
    reoptimise: int = 0
    reoptimise_sweeps: int = 1


@dataclass(frozen=True)
class SampledDevice:
    """The device a certified case corrects: ``fab`` (with its supercell coupling model), its coupled pupil
    ``cp`` made with ``pert`` on ``grid``, the ``sensor``; ``design``: the device's own design (nominal widths),
    needed to re-choose its atoms."""

    fab: Any
    cp: Any
    sensor: SensorSpec
    grid: int
    pert: Perturbation = Perturbation()
    design: Any = None


def _mean(rows, key):
    return float(np.mean([abs(r[key]) if key == "focal_shift_mm" else r[key] for r in rows]))


def _progress_lines(log, t0: float, levels: int, what: str, steps: str = ""):
    """A progress callback that logs a line per tenth of each pass (one pass per low-fidelity level)."""
    said = {"pass": 0, "last": -1, "tenths": set()}

    def progress(d, n):
        if d < said["last"]:
            said["pass"], said["tenths"] = said["pass"] + 1, set()
        said["last"] = d
        if d * 10 // max(n, 1) not in said["tenths"]:
            said["tenths"].add(d * 10 // max(n, 1))
            k, L = said["pass"], levels
            where = f"level {k + 1}" if not steps else f"{steps} {k // L + 1}, level {k % L + 1}"
            log(f"    {what}, {where}: {d}/{n} ({time.perf_counter() - t0:.0f} s)")
    return progress


def certified_case(device: SampledDevice, settings: CertifiedSettings = CertifiedSettings(), partial=None, *,
                   run: Execution = SERIAL, label: str = CERTIFIED_LABEL, return_deltas: bool = False):
    """``device.fab`` (with its supercell coupling model) under the certified model: its coupled pupil
    ``device.cp`` plus the certified model's correction ``t_peds - t_coupled``, measured on
    ``settings.supercells`` supercells drawn uniformly (seeded) from the device's complete ones in
    ``settings.replicates`` equal replicates (:mod:`metadesign.sensing.sampled`), with the widths, etch depth
    and wall angle of ``device.pert`` (``cp`` made with it, on ``device.grid``; the pillars' unit cells as the
    device's, the low-fidelity solves at the etched height, with sloped walls in ``settings.taper_slices``
    slices (0: vertical, the widths at mid-height)).  The case's metrics, their jackknife standard errors, and
    the corrections' statistics (in units of the pillars' rms |t|, as the certification); with
    ``return_deltas``, also the replicates' correction pupils (``(report, deltas, deltas with the ring or
    None)``: the sampled device's frames, :func:`~metadesign.sensing.sampled.sampled_frames`).  Solves under
    ``partial`` (resumable), on ``run``'s workers or scheduler; lines to ``run.log``.  The ring and the re-chosen atoms: :class:`CertifiedSettings`."""
    t0 = time.perf_counter()
    fab, pert, st = device.fab, device.pert, settings
    if fab.coupling is None:
        raise ValueError("certified_case: the device needs its coupling model (the control variate)")
    if st.reoptimise and device.design is None:
        raise ValueError("certified_case: re-optimising the atoms needs the device's design")
    if st.reoptimise and replace(pert, seed=0) != Perturbation():
        raise ValueError("certified_case: re-optimising the atoms is for the nominal device (no width, etch or wall "
                         "error)")
    peds = st.peds
    pm = peds if isinstance(peds, PedsModel) else load_peds(peds if peds is not None else find_peds(fab.lib), fab.lib)
    ids = eligible_supercells(fab)
    replicates = st.replicates
    m = st.supercells // replicates
    if m < 1 or replicates < 3:
        raise ValueError("certified_case: at least three replicates of one supercell each")
    pick = ids[np.random.default_rng(st.seed).integers(0, len(ids), m * replicates)]
    w = supercell_widths(fab, pick, replace(pert, height=0.0, sidewall_deg=90.0), device.grid)  # at mid-height
    tu = unit_t_as_made(fab.lib, w[..., 0], w[..., 1], pert, fab.fab_lib)
    t_pair = coupling_t(fab.coupling, w, tu)
    stack = replace(fab.lib.stack, height=fab.lib.stack.height + pert.height)
    taper = (pert.sidewall_deg, st.taper_slices) if pert.sidewall_deg != 90.0 and st.taper_slices else None
    lines = lambda what, steps="": _progress_lines(run.log, t0, len(pm.harmonics), what, steps)  # noqa: E731
    t_cert = certified_t(fab.lib, w, partial, pm, workers=run.workers, scheduler=run.scheduler,
                         progress=lines("certified solves"), stack=stack, t_unit=tu, taper=taper)
    delta = (t_cert - t_pair).astype(np.complex64)
    ring = None
    if st.ring_supercells:
        ring = _ring_sample(device, st, (pick, w, tu, t_cert), ids, pm,
                            dict(partial=partial, stack=stack, taper=taper, progress=lines("ring windows"), run=run))
    t_solved = time.perf_counter()
    plain = _replicate_pupils(device, pick, delta, m, replicates, len(ids))
    deltas = plain
    if ring is not None:  # the ring's sub-sample, weighted for its own size, on top of the same replicates
        ring_rep, ring_ids, ring_delta, ring_weight, ring_rows = ring
        deltas = [_plus_pupil(d, delta_pupil(fab, device.cp.z, device.grid, ring_ids[ring_rows[r]],
                                             ring_delta[ring_rows[r]], ring_weight)) for r, d in enumerate(plain)]
    rel = relative_error(t_cert, t_pair, tu)  # the certification's measure: in units of the pillars' rms |t|
    rep = {
        "label": label,
        "coupling": "certified (PEDS), sampled", "seconds": time.perf_counter() - t0,
        "seconds_solves": t_solved - t0, **_sampled_metrics(device.cp, plain, device.sensor, fab),
        "sampling": {"supercells": int(m * replicates), "replicates": int(replicates), "seed": int(st.seed),
                     "eligible_supercells": len(ids), "distinct_sampled": len(np.unique(pick))},
        "peds": {"harmonics": list(pm.harmonics), "library_sha256": pm.library_sha256,
                 "taper": list(taper) if taper else None,
                 "coefficients": [[float(c.real), float(c.imag)] for c in np.atleast_1d(pm.coef)]},
        "ring": None,
        "correction": {"mean_relative": [float(v) for v in rel.mean(0)],
                       "p90_relative": [float(v) for v in np.percentile(rel, 90, axis=0)],
                       "mean_complex": [[float(v.real), float(v.imag)] for v in delta.mean(0)]},
    }
    if ring is not None:  # the same sample with the ring added: the ring's effect on matched replicates
        ring_case = _matched_case(device, deltas, rep, ring_rep)
        rep["with_ring"] = {**{k: v for k, v in rep.items() if k not in ("with_ring", "_loo")},
                            "label": label.replace("(PEDS", "(PEDS, overlapping windows"),
                            "coupling": "certified (PEDS on overlapping windows), sampled", "ring": ring_rep,
                            "seconds": time.perf_counter() - t0, **ring_case}
    if st.reoptimise:  # the same replicates with the re-chosen atoms: their effect on a matched sample
        reo_rep, D = _reoptimise_sample(device, st, (pick, w, t_cert), pm, f"{partial}/reoptimise",
                                        run.replace(progress=lines("re-optimising", "step")))
        reo_case = _matched_case(device, _replicate_pupils(device, pick, D, m, replicates, len(ids)), rep, reo_rep)
        rep["reoptimised"] = {**{k: v for k, v in rep.items() if k not in ("with_ring", "_loo", "correction", "ring")},
                              "label": f"{label}, atoms re-chosen under it",
                              "coupling": "certified (PEDS), sampled; atoms re-chosen under it",
                              "reoptimise": reo_rep, "seconds": time.perf_counter() - t0, **reo_case}
    rep.pop("_loo")
    return (rep, plain, deltas if ring is not None else None) if return_deltas else rep


def _replicate_pupils(device: SampledDevice, pick, delta, m: int, replicates: int, eligible: int) -> list:
    """Each replicate's correction pupil: its ``m`` supercells' corrections, weighted for the device."""
    return [delta_pupil(device.fab, device.cp.z, device.grid, pick[r * m:(r + 1) * m], delta[r * m:(r + 1) * m],
                        eligible / m) for r in range(replicates)]


def _matched_case(device: SampledDevice, deltas: list, rep: dict, effect_of: dict) -> dict:
    """The sampled metrics of the replicate pupils ``deltas``, and (into ``effect_of["effect"]``) their
    difference from the plain case ``rep`` on the same replicates, with its jackknife standard error."""
    case = _sampled_metrics(device.cp, deltas, device.sensor, device.fab)
    a, b = case.pop("_loo"), rep["_loo"]
    effect_of["effect"] = {k: {"mean": case["mean"][k] - rep["mean"][k],
                               "stderr": jackknife_se(np.subtract(a[k], b[k]))} for k in SPOT_KEYS}
    return case


def _ring_sample(device: SampledDevice, st: CertifiedSettings, sample: tuple, ids, pm, solve: dict):
    """The neighbour ring by overlapping windows on the first ``ring_supercells / replicates`` supercells of
    every replicate (:func:`certified_case`; ``sample = (pick, widths, unit t, certified t)``): ``(report,
    supercell ids, ring terms, weight, rows per replicate)``; ``solve``: how the certified model solves
    (partial, stack, taper, progress, run)."""
    pick, w, tu, t_cert = sample
    fab, pert, replicates = device.fab, device.pert, st.replicates
    m = len(pick) // replicates
    k = min(m, st.ring_supercells // replicates)
    if k < 1:
        raise ValueError("certified_case: at least one ring supercell per replicate")
    sub = np.concatenate([np.arange(r * m, r * m + k) for r in range(replicates)])
    C2 = fab.n_cells // 2
    s_ids = pick[sub]
    corners = [s_ids + 1, s_ids + C2, s_ids + C2 + 1]  # the neighbours at +x, +y, +x+y
    whole = (s_ids % C2 + 1 < C2) & np.all([np.isin(c, ids) for c in corners], axis=0)
    nw = int(whole.sum())  # the three neighbours' widths in one pass over the device's rows
    wn = supercell_widths(fab, np.concatenate([c[whole] for c in corners]),
                          replace(pert, height=0.0, sidewall_deg=90.0), device.grid)
    wq = [w[sub][whole]] + [wn[i * nw:(i + 1) * nw] for i in range(3)]
    nbhd = np.concatenate([np.concatenate([wq[0], wq[1]], 2), np.concatenate([wq[2], wq[3]], 2)], 1)[:, :3, :3]
    win = neighbour_windows(nbhd).reshape(-1, 2, 2, 2)
    solve["run"].log(f"    neighbour ring: {len(win)} straddling windows of {int(whole.sum())} supercells ...")
    t_r = time.perf_counter()
    tu_w = unit_t_as_made(fab.lib, win[..., 0], win[..., 1], pert, fab.fab_lib)
    t_win = certified_t(fab.lib, win, f"{solve['partial']}/ring", pm, workers=solve["run"].workers,
                        scheduler=solve["run"].scheduler, progress=solve["progress"], stack=solve["stack"],
                        t_unit=tu_w, taper=solve["taper"]).reshape(-1, 3, 2)
    rterm = np.zeros((len(sub), 2), np.complex128)
    rterm[whole] = window_ring(t_win, t_cert[sub][whole])
    ring_rows = [np.arange(r * k, (r + 1) * k) for r in range(replicates)]
    rel_r = np.abs(rterm) / np.sqrt((np.abs(tu[sub]) ** 2).mean((1, 2)))
    ring_rep = {"supercells": int(len(sub)), "with_neighbours": int(whole.sum()), "windows": int(len(win)),
                "seconds": time.perf_counter() - t_r, "mean_relative": [float(v) for v in rel_r.mean(0)],
                "p90_relative": [float(v) for v in np.percentile(rel_r, 90, axis=0)],
                "mean_complex": [[float(v.real), float(v.imag)] for v in rterm.mean(0)]}
    return ring_rep, s_ids, rterm.astype(np.complex64), len(ids) / k, ring_rows


def _pillar_t(fab, w: np.ndarray) -> np.ndarray:
    """(n, 2, 2, 2 pol) each pillar's ``t`` under the device's coupling model (its unit cell plus its coupling
    term, as the coupled pupil has it) for nominal supercells ``w`` (n, 2, 2, 2) m: the supercells side by
    side in one strip of two rows."""
    n = len(w)
    tu = unit_t_as_made(fab.lib, w[..., 0], w[..., 1], Perturbation(), fab.fab_lib)
    strip = lambda x: np.swapaxes(x, 0, 1).reshape(2, 2 * n, *x.shape[3:])  # noqa: E731  [s, r, c] -> [r, 2s + c]
    t = couple_supercells(strip(tu).astype(np.complex64), strip(w), np.ones((2, 2 * n), bool), fab.coupling)
    return np.swapaxes(np.asarray(t).reshape(2, n, 2, 2), 0, 1)


def _reoptimise_sample(device: SampledDevice, st: CertifiedSettings, sample: tuple, pm, partial: str | Path,
                       run: Execution):
    """The sampled supercells' atoms re-chosen under the certified model (``reoptimise`` of
    :func:`certified_case`; ``sample = (pick, widths, t_certified)``): ``(report, per-pillar correction (n, 2,
    2, 2) to the coupled pupil)``: each pillar moves from its coupled ``t`` among the starting atoms to its
    coupled ``t`` among the new ones, and the supercell's mean from there to the certified model's ``t`` of
    the new atoms."""
    fab, design, K, sweeps = device.fab, device.design, st.reoptimise, st.reoptimise_sweeps
    pick, w, t_cert = sample
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
        return certified_t(fab.lib, aw[tuples], partial, pm, workers=run.workers, scheduler=run.scheduler,
                           progress=run.progress)

    run.log(f"    re-optimising {len(a)} supercells under the certified model: {nbr.shape[1]} candidates per "
            f"position, {sweeps} sweep(s), {len(a) * 4 * sweeps * (nbr.shape[1] - 1)} solves ...")
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
