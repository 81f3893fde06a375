"""The measured results the documentation quotes, read from the committed JSON records: one source.

* :data:`MEASURED` names each quoted number: the committed JSON file it is read from, where in it, the
  format it is quoted in (and a scale: seconds to minutes, a fraction to percent).
* :func:`measured` formats them all; ``docs/conf.py`` hands them to MyST as substitutions, so the results
  page writes ``{{ cc_eff }}`` and the build puts in what ``sensing/coupling-check/coupling-check.json``
  holds (a missing file or key fails the build).
* The README, which GitHub shows as it is, quotes some of the same numbers: ``tests/test_docs_numbers.py``
  checks each of its quotes against :func:`measured`.
* As a Sphinx extension, the role ``{reproduce}`\\`metadesign library coupling-check ...\\``` writes a
  command as code that links to its entry in the CLI reference (``python benchmarks/...``: to the
  benchmarks page).

A path in a record: keys separated by ``/`` (keys may hold dots: ``by_rytov/0.5-0.6``), ``name[i]`` a list
item, ``name[field=value]`` the list item whose ``field`` is ``value``.
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache, lru_cache
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Q:
    """A number in a committed record: ``file`` (repository-relative), ``path`` in it, ``fmt``, ``scale``."""

    file: str
    path: str
    fmt: str = "{:.3f}"
    scale: float = 1.0

    def value(self, repo: Path = REPO) -> float:
        return lookup(_record(str(repo / self.file)), self.path) * self.scale


@dataclass(frozen=True)
class D:
    """A number derived from several (a difference, a ratio, a range end): ``fn`` of the records' getter."""

    fn: Callable
    fmt: str = "{:.3f}"

    def value(self, repo: Path = REPO) -> float:
        def get(file: str, path: str | None = None):  # a number, or (no path) the whole record
            rec = _record(str(repo / file))
            return rec if path is None else lookup(rec, path)

        return float(self.fn(get))


@cache
def _record(path: str):
    return json.loads(Path(path).read_text())


def lookup(obj, path: str) -> float:
    """The number at ``path`` in ``obj`` (a KeyError naming the missing part otherwise)."""
    for part in path.split("/"):
        m = re.fullmatch(r"(.*?)\[(.+)\]", part)
        key, sel = (m.group(1), m.group(2)) if m else (part, None)
        if key:
            if not isinstance(obj, dict) or key not in obj:
                raise KeyError(f"{path}: no {key!r}")
            obj = obj[key]
        if sel is not None:
            if "=" in sel:
                field, want = sel.split("=", 1)
                hits = [x for x in obj if str(x.get(field)) == want]
                if len(hits) != 1:
                    raise KeyError(f"{path}: {len(hits)} items with {field} = {want}")
                obj = hits[0]
            else:
                obj = obj[int(sel)]
    if isinstance(obj, bool) or not isinstance(obj, (int, float)):
        raise KeyError(f"{path}: not a number ({obj!r})")
    return float(obj)


def _five(file: str, noise: str = "5", what: str = "captured_fraction") -> Q:
    return Q(file, f"by_noise/gaussian:{noise}/{what}")


CD = "sensing/codesign-demo/"
CC = "sensing/coupling-check{}/coupling-check.json"
WIDE = "layouts/wide-100mm-run.json"
PEDS = "library/paper-peds.json"
PATCHES = "library/paper-5mm-patches.json"
COMPARE = "sensing/compare-demo/compare.json"
TOL = "sensing/tolerance-demo-out/tolerance.json"
TRANSFER = "sensing/transfer-demo-out/transfer.json"
RT = "sensing/realtime-bench/results.json"
LOOP = "sensing/loop-demo-out/loop.json"
LOOP_G = "sensing/loop-demo-gain-out/loop.json"
LOOP_N = "sensing/loop-demo-loopnet-out/loop.json"
LOOP_W = "sensing/loop-demo-w48-out/loop.json"
LOOP_Z = "sensing/loop-demo-w48-lat0-out/loop.json"
LOOP_T = "sensing/loop-demo-w48-tt-out/loop.json"
LOOP_P = "sensing/loop-demo-w48-peak-out/loop.json"
LOOP_K = "sensing/loop-demo-w48-leak-out/loop.json"
MAP = "sensing/loop-map-out/map.json"
MAP_W = "sensing/loop-map-w48-out/map.json"
PC, PC_RT = "sensing/polcam-demo/polcam.json", "sensing/polcam-retrained/polcam.json"
_PC_CAMS = {"ideal": "ideal", "er10_15": "ER 10, 15 um", "er10_30": "ER 10, 30 um", "er30_75": "ER 30, 7.5 um"}


def _cc(run: str, case: str, what: str, stat: str = "mean", fmt: str = "{:.4f}", scale: float = 1.0) -> Q:
    return Q(CC.format(run), f"cases/{case}/{stat}/{what}", fmt, scale)


def _loop_band(m: str, modes: str, f_max: float | None = 50.0, record: str = "") -> D:
    """A loop's (default: the demo loop's, searched gains) modal PSD power of method ``m`` in ``(0, f_max]`` Hz
    over the open loop's, ``modes`` "tt" (Noll 2, 3) or "ho" (Noll 4 on); ``f_max`` None: the variance itself
    (rad^2, every bin, all the record's modes)."""
    def power(rec, name, sel, top):
        p = rec["methods"][name]["modal_psd"]
        df = p["f_hz"][1] - p["f_hz"][0]
        return df * sum(v for j, row in zip(p["noll"], p["psd_rad2_hz"]) if sel(j)
                        for f, v in zip(p["f_hz"], row) if top is None or 0 < f <= top)

    def fn(get):
        rec = get(record or LOOP_G)
        if f_max is None:
            return power(rec, m, lambda j: True, None)
        sel = (lambda j: j <= 3) if modes == "tt" else (lambda j: j >= 4)
        return power(rec, m, sel, f_max) / power(rec, "open", sel, f_max)
    return D(fn, "{:.2f}" if f_max is not None else "{:.3f}")


def _modal_var(rec: dict, m: str, noll: int) -> float:
    """Method ``m``'s variance (rad^2) of Zernike ``noll`` in a loop record: its modal PSD over every bin."""
    p = rec["methods"][m]["modal_psd"]
    return (p["f_hz"][1] - p["f_hz"][0]) * sum(p["psd_rad2_hz"][p["noll"].index(noll)])


def _tol_range(end: Callable, when: str) -> D:
    """The lowest or highest U-Net NPiB over the tolerance study's cases, before or after fine-tuning."""
    def fn(get):
        return end(r[when]["npib_unet"] for r in get(TOL)["rows"] if r.get(when))
    return D(fn)


MEASURED: dict[str, Q | D] = {
    # co-design (demo scale): captured fraction at 5 % noise, each model through its own diversity
    "cd_learned_5": _five(CD + "evaluation-demo.json"),
    "cd_paper_5": _five(CD + "evaluation-paper-fixed.json"),
    "cd_random_5": _five(CD + "evaluation-random-fixed.json"),
    # held out (seed 20261125, 640 samples), captured fraction
    **{f"ho_{k}_{n}": _five(CD + f"heldout-{f}.json", n) for k, f in (
        ("cd_unet", "codesign-unet"), ("paper_unet", "paper-unet"), ("cd_refine", "codesign-refine"),
        ("paper_refine", "paper-refine"), ("deep", "codesign-refine-deep"), ("wide_unet", "codesign-wide-unet"),
        ("wide_refine", "codesign-wide-refine"), ("wide_refine9", "codesign-wide-refine9"),
        ("paper_k6", "paper-refine-k6")) for n in ("0", "2", "5", "10")},
    **{f"ho_{k}_r56": _five(CD + f"heldout-{f}.json", "5", "by_rytov/0.5-0.6/captured_fraction") for k, f in (
        ("deep", "codesign-refine-deep"), ("cd_refine", "codesign-refine"), ("wide_refine", "codesign-wide-refine"),
        ("wide_refine9", "codesign-wide-refine9"))},
    # branch points: the vortex-free phase conjugate (held out, the deep refiner's record)
    "vf_all": Q(CD + "heldout-codesign-refine-deep.json", "vortex_free/captured_fraction"),
    "vf_r02": Q(CD + "heldout-codesign-refine-deep.json", "by_rytov/0-0.2/vortex_free/captured_fraction", "{:.2f}"),
    "vf_r56": Q(CD + "heldout-codesign-refine-deep.json", "by_rytov/0.5-0.6/vortex_free/captured_fraction", "{:.2f}"),
    "bp_mean": Q(CD + "heldout-codesign-refine-deep.json", "vortex_free/branch_points_mean", "{:.1f}"),
    # the one-shot U-Net on twice the paper's ladder (twin protocol)
    "x2_5": _five(CD + "evaluation-paper-fixed-x2.json"),
    "x2_cont_5": _five(CD + "evaluation-paper-fixed-x2-continued.json"),
    # the PEDS surrogate, certified on 250 held-out supercells (mean / p90 of rms |t|)
    "peds_mean": Q(PEDS, "certification/mean_both"),
    "peds_p90": Q(PEDS, "certification/p90_both"),
    "lpa_mean": Q(PEDS, "certification/lpa_mean_both"),
    "lpa_p90": Q(PEDS, "certification/lpa_p90_both"),
    "net_mean": Q(PEDS, "certification/networks/env, on paper-supercells-fast.npz/mean_both"),
    "net_p90": Q(PEDS, "certification/networks/env, on paper-supercells-fast.npz/p90_both"),
    "coupling_mean": Q(PEDS, "certification/networks/paper-coupling, on paper-supercells.npz/mean_both", "{:.2f}"),
    "coupling_p90": Q(PEDS, "certification/networks/paper-coupling, on paper-supercells.npz/p90_both", "{:.2f}"),
    "lpa_mean2": Q(PEDS, "certification/lpa_mean_both", "{:.2f}"),
    "lpa_p90_2": Q(PEDS, "certification/lpa_p90_both", "{:.2f}"),
    "peds_s": Q(PEDS, "certification/cost/seconds_per_supercell_core", "{:.2f}"),
    "peds_cheaper": D(lambda g: g(PEDS, "certification/cost/label_seconds_per_supercell_core")
                      / g(PEDS, "certification/cost/seconds_per_supercell_core"), "{:.0f}"),
    # the paper device under the certified model, sampled (sensing/coupling-check/)
    "cc_eff": _cc("", "certified", "spot_efficiency"),
    "cc_eff_se": _cc("", "certified", "spot_efficiency", "stderr"),
    "cc_coupled_eff": _cc("", "coupled", "spot_efficiency"),
    "cc_lpa_eff": _cc("", "lpa", "spot_efficiency"),
    "cc_strehl": _cc("", "certified", "spot_strehl", fmt="{:.3f}"),
    "cc_strehl_se": _cc("", "certified", "spot_strehl", "stderr", "{:.3f}"),
    "cc_coupled_strehl": _cc("", "coupled", "spot_strehl", fmt="{:.3f}"),
    "cc_lpa_strehl": _cc("", "lpa", "spot_strehl", fmt="{:.3f}"),
    "cc_focal": _cc("", "certified", "focal_shift_mm", fmt="{:.0f}", scale=1e3),
    "cc_focal_se": _cc("", "certified", "focal_shift_mm", "stderr", "{:.0f}", 1e3),
    "cc_coupled_focal": _cc("", "coupled", "focal_shift_mm", fmt="{:.0f}", scale=1e3),
    "cc_lpa_focal": _cc("", "lpa", "focal_shift_mm", fmt="{:.0f}", scale=1e3),
    "cc_min": Q(CC.format(""), "cases/certified/seconds", "{:.1f}", 1 / 60),
    "cc_loss_pct": D(lambda g: 100 * (1 - g(CC.format(""), "cases/certified/mean/spot_efficiency")
                                      / g(CC.format(""), "cases/lpa/mean/spot_efficiency")), "{:.1f}"),
    "cc_coupled_loss_pct": D(lambda g: 100 * (1 - g(CC.format(""), "cases/coupled/mean/spot_efficiency")
                                              / g(CC.format(""), "cases/lpa/mean/spot_efficiency")), "{:.1f}"),
    "cc_strehl_drop": D(lambda g: g(CC.format(""), "cases/lpa/mean/spot_strehl")
                        - g(CC.format(""), "cases/certified/mean/spot_strehl")),
    "cc_coupled_strehl_drop": D(lambda g: g(CC.format(""), "cases/lpa/mean/spot_strehl")
                                - g(CC.format(""), "cases/coupled/mean/spot_strehl")),
    # the demo U-Net through it (64 test samples, 5 % noise)
    "cc_npib": Q(CC.format(""), "downstream/certified/npib_unet"),
    "cc_npib_se": Q(CC.format(""), "downstream/certified/npib_unet_se"),
    "cc_npib_bias": Q(CC.format(""), "downstream/certified/npib_unet_bias"),
    "cc_comp_npib": Q(CC.format(""), "downstream/compensated_certified/npib_unet"),
    "cc_comp_npib_se": Q(CC.format(""), "downstream/compensated_certified/npib_unet_se"),
    "cc_lpa_npib": Q(CC.format(""), "downstream/lpa/npib_unet"),
    "cc_coupled_npib": Q(CC.format(""), "downstream/coupled/npib_unet"),
    # etch depth -30 / +30 nm
    **{f"etch{t}_{k}": _cc(f"-etch{r}", c, "spot_efficiency", s) for t, r in (("m30", "-30"), ("p30", "30"))
       for k, c, s in (("eff", "certified", "mean"), ("se", "certified", "stderr"), ("lpa", "lpa", "mean"),
                       ("coupled", "coupled", "mean"))},
    "etch_under_gain_pct": D(lambda g: 100 * (g(CC.format("-etch-30"), "cases/certified/mean/spot_efficiency")
                                              / g(CC.format(""), "cases/certified/mean/spot_efficiency") - 1), "{:.0f}"),
    "etch_over_loss_pct": D(lambda g: 100 * (1 - g(CC.format("-etch30"), "cases/certified/mean/spot_efficiency")
                                             / g(CC.format(""), "cases/certified/mean/spot_efficiency")), "{:.0f}"),
    # 88 degree sidewalls
    "wall_eff": _cc("-wall88", "certified", "spot_efficiency"),
    "wall_se": _cc("-wall88", "certified", "spot_efficiency", "stderr"),
    "wall_lpa": _cc("-wall88", "lpa", "spot_efficiency"),
    "wall_coupled": _cc("-wall88", "coupled", "spot_efficiency"),
    "wall_strehl": _cc("-wall88", "certified", "spot_strehl", fmt="{:.3f}"),
    "wall_strehl_se": _cc("-wall88", "certified", "spot_strehl", "stderr", "{:.3f}"),
    # the neighbour ring: 32 patches (mean / p90 of rms |t|, both polarisations)
    "ring_beyond_mean": Q(PATCHES, "beyond_2x2_mean_both"),
    "ring_beyond_p90": Q(PATCHES, "beyond_2x2_p90_both"),
    "ring_exact_mean": Q(PATCHES, "windows_exact/mean_both"),
    "ring_exact_p90": Q(PATCHES, "windows_exact/p90_both"),
    "ring_peds_mean": Q(PATCHES, "windows_peds/mean_both"),
    "ring_peds_p90": Q(PATCHES, "windows_peds/p90_both"),
    "ring_lf_mean": Q(PATCHES, "ring/calibrated_held_out_mean_both"),
    "ring_lf_p90": Q(PATCHES, "ring/calibrated_held_out_p90_both"),
    # the device with its ring (sensing/coupling-check-ring/)
    "ringdev_eff": _cc("-ring", "certified_ring", "spot_efficiency"),
    "ringdev_eff_se": _cc("-ring", "certified_ring", "spot_efficiency", "stderr"),
    "ringdev_strehl": _cc("-ring", "certified_ring", "spot_strehl", fmt="{:.3f}"),
    "ringdev_strehl_se": _cc("-ring", "certified_ring", "spot_strehl", "stderr", "{:.3f}"),
    "ringdev_focal": _cc("-ring", "certified_ring", "focal_shift_mm", fmt="{:.0f}", scale=1e3),
    "ringdev_focal_se": _cc("-ring", "certified_ring", "focal_shift_mm", "stderr", "{:.0f}", 1e3),
    "ringdev_plain_eff": _cc("-ring", "certified", "spot_efficiency"),
    "ringdev_plain_strehl": _cc("-ring", "certified", "spot_strehl", fmt="{:.3f}"),
    "ringdev_plain_focal": _cc("-ring", "certified", "focal_shift_mm", fmt="{:.0f}", scale=1e3),
    # the compensated design's atoms re-chosen under the certified model (sensing/coupling-check-reoptimised/)
    "reopt_eff": _cc("-reoptimised", "certified_reoptimised", "spot_efficiency"),
    "reopt_eff_se": _cc("-reoptimised", "certified_reoptimised", "spot_efficiency", "stderr"),
    "reopt_start_eff": _cc("-reoptimised", "certified", "spot_efficiency"),
    "reopt_start_eff_se": _cc("-reoptimised", "certified", "spot_efficiency", "stderr"),
    "reopt_strehl": _cc("-reoptimised", "certified_reoptimised", "spot_strehl", fmt="{:.3f}"),
    "reopt_start_strehl": _cc("-reoptimised", "certified", "spot_strehl", fmt="{:.3f}"),
    "reopt_gain_pct": D(lambda g: 100 * (g(CC.format("-reoptimised"), "cases/certified_reoptimised/mean/spot_efficiency")
                                         / g(CC.format("-reoptimised"), "cases/certified/mean/spot_efficiency") - 1),
                        "{:.0f}"),
    # width bias -10 ... +10 nm and 5 nm jitter under the certified model (spot efficiency)
    **{f"bias{t}_{k}": _cc(r, c, "spot_efficiency", s) for t, r in (
        ("m10", "-bias-10"), ("m5", "-bias-5"), ("0", ""), ("p5", "-bias5"), ("p10", "-bias10"), ("j5", "-jitter5"))
       for k, c, s in (("eff", "certified", "mean"), ("se", "certified", "stderr"), ("coupled", "coupled", "mean"))},
    "bias_se_lo": D(lambda g: min(g(CC.format(r), "cases/certified/stderr/spot_efficiency")
                                  for r in ("-bias-10", "-bias-5", "", "-bias5", "-bias10")), "{:.4f}"),
    "bias_se_hi": D(lambda g: max(g(CC.format(r), "cases/certified/stderr/spot_efficiency")
                                  for r in ("-bias-10", "-bias-5", "", "-bias5", "-bias10")), "{:.4f}"),
    # the 10 cm device (layouts/wide-100mm-run.json)
    "wide_pillars_e10": Q(WIDE, "pillars", "{:.2f}", 1e-10),
    "wide_pillars_1e10": Q(WIDE, "pillars", "{:.1f}", 1e-10),
    "wide_numpy_min": Q(WIDE, "seconds", "{:.1f}", 1 / 60),
    "wide_numpy_gb": Q(WIDE, "peak_bytes_process_tree", "{:.2f}", 1e-9),
    "wide_build_min": Q(WIDE, "compiled_kernels/build_10cm/seconds", "{:.1f}", 1 / 60),
    "wide_build_gb": Q(WIDE, "compiled_kernels/build_10cm/peak_bytes_process_tree", "{:.2f}", 1e-9),
    "wide_verify_min": Q(WIDE, "verify_stream/seconds", "{:.1f}", 1 / 60),
    "wide_verify_gb": Q(WIDE, "verify_stream/peak_bytes_process_tree", "{:.1f}", 1e-9),
    "wide_verify_gb2": Q(WIDE, "verify_stream/peak_bytes_process_tree", "{:.2f}", 1e-9),
    "wide_psf_min": Q(WIDE, "compiled_kernels/psf_10cm_1_worker/seconds", "{:.1f}", 1 / 60),
    "wide_psf_gb": Q(WIDE, "compiled_kernels/psf_10cm_1_worker/peak_bytes_process_tree", "{:.2f}", 1e-9),
    "wide25_min": Q(WIDE, "compiled_kernels/scaling_2p5cm/two_workers_seconds", "{:.2f}", 1 / 60),
    "wide25_speedup": Q(WIDE, "compiled_kernels/scaling_2p5cm/speedup", "{:.2f}"),
    # the baselines on the demo set (sensing/compare-demo/, 320 test samples, 5 % noise)
    **{f"cmp_{k}": Q(COMPARE, f"summary/npib/{k}") for k in (
        "none", "shack_hartmann", "retrieval", "unet", "hybrid", "phase_conjugate", "complex_conjugate")},
    "cmp_unet_ms": Q(COMPARE, "summary/latency_ms/unet", "{:.1f}"),
    "cmp_sh_ms": Q(COMPARE, "summary/latency_ms/shack_hartmann", "{:.1f}"),
    "cmp_retrieval_s": Q(COMPARE, "summary/latency_ms/retrieval", "{:.1f}", 1e-3),
    "cmp_hybrid_s": Q(COMPARE, "summary/latency_ms/hybrid", "{:.2f}", 1e-3),
    "cmp_retrieval_10ms": Q(COMPARE, "summary/budgets_ms/10/retrieval"),
    "cmp_retrieval_100ms": Q(COMPARE, "summary/budgets_ms/100/retrieval"),
    "cmp_hybrid_100ms": Q(COMPARE, "summary/budgets_ms/100/hybrid"),
    # reconstruction-level fab tolerance (sensing/tolerance-demo-out/)
    "tol_nominal": Q(TOL, "rows[case=nominal]/before/npib_unet"),
    "tol_nominal_cf": Q(TOL, "rows[case=nominal]/before/captured_fraction", "{:.2f}"),
    "tol_lo": _tol_range(min, "before"),
    "tol_hi": _tol_range(max, "before"),
    "tol_ft_lo": _tol_range(min, "after"),
    "tol_ft_hi": _tol_range(max, "after"),
    "tol_none": Q(TOL, "rows[case=nominal]/before/npib_none"),
    "tol_pc": Q(TOL, "rows[case=nominal]/before/npib_phase_conjugate"),
    # fab-to-lab transfer (sensing/transfer-demo-out/, 320 imported test captures)
    **{f"tr_{k}": Q(TRANSFER, f"rows/{k}/npib_unet") for k in ("unadapted", "finetuned", "scratch")},
    **{f"tr_{k}_cf": Q(TRANSFER, f"rows/{k}/captured_fraction", "{:.2f}") for k in ("unadapted", "finetuned", "scratch")},
    "tr_none": Q(TRANSFER, "rows/unadapted/npib_none"),
    # real time (sensing/realtime-bench/, benchmarks/bench_realtime.py: one core, batch 1, 320 test samples, 5 %)
    **{f"rt_{k}_cf": Q(RT, f"estimators/{k}/captured_fraction") for k in (
        "unet", "refine", "refine_k1", "shack_hartmann", "linear", "realtime_ort", "realtime_ort_int8",
        "realtime_commands")},
    **{f"rt_{k}_us": Q(RT, f"estimators/{k}/latency/median_us", "{:,.0f}") for k in (
        "unet", "unet_ort", "refine", "refine_k1", "shack_hartmann", "linear", "realtime_torch", "realtime_compile",
        "realtime_ort", "realtime_ort_int8", "realtime_commands")},
    **{f"rt_{k}_e2e": Q(RT, f"estimators/{k}/end_to_end_median_us", "{:,.0f}") for k in (
        "unet", "refine", "shack_hartmann", "realtime_commands")},
    "rt_cf_lo": Q(RT, "estimators/realtime_commands/cf_ci95[0]"),
    "rt_cf_hi": Q(RT, "estimators/realtime_commands/cf_ci95[1]"),
    "rt_speedup": Q(RT, "verdict/speedup_vs_unet", "{:.0f}"),
    "rt_cam_us": Q(RT, "camera_to_tensor/median_us", "{:,.0f}"),
    "rt_cam_rt_us": Q(RT, "camera_to_tensor_realtime/median_us", "{:,.0f}"),
    "rt_e2e_speedup": Q(RT, "verdict/end_to_end_speedup_vs_unet", "{:.0f}"),
    "rt_cam_ref_us": Q(RT, "camera_to_tensor_reference/median_us", "{:,.0f}"),
    "rt_fit_us": Q(RT, "dm_fit/median_us", "{:,.0f}"),
    "rt_compile_s": Q(RT, "estimators/realtime_compile/compile_s", "{:.0f}"),
    **{f"rt_jit_{w}_{k}": Q(RT, f"jitter/{w}/{k}_us", "{:,.0f}") for w in ("idle", "busy_neighbours")
       for k in ("median", "p99", "max")},
    # the demo loop with every estimator at its measured latency (sensing/loop-demo-out/, metadesign loop loop-demo)
    **{f"loop_{m}_npib": Q(LOOP, f"methods/{m}/npib_mean") for m in (
        "unet", "refine", "realtime", "shack_hartmann", "ideal", "fitted", "conjugate", "open")},
    **{f"loop_{m}_delay": Q(LOOP, f"methods/{m}/delay_frames", "{:.1f}") for m in (
        "unet", "refine", "realtime", "shack_hartmann")},
    **{f"loop_{m}_ms": Q(LOOP, f"methods/{m}/latency_ms", "{:.2f}") for m in (
        "unet", "refine", "realtime", "shack_hartmann")},
    "loop_fg": Q(LOOP, "turbulence/greenwood_hz", "{:.0f}"),
    "loop_rt_vs_ideal": Q(LOOP, "verdict/vs_ideal", "{:.2f}"),
    **{f"loopg_{m}_npib": Q(LOOP_G, f"methods/{m}/npib_mean") for m in ("realtime", "ideal", "open")},
    **{f"loopg_{m}_gain": Q(LOOP_G, f"methods/{m}/gain") for m in ("realtime", "ideal")},
    "loopg_rt_fade": Q(LOOP_G, "methods/realtime/fades/probability"),
    "loopg_rt_vs_ideal": Q(LOOP_G, "verdict/vs_ideal", "{:.2f}"),
    # the demo loop with the network trained on closed-loop residuals (sensing/loop-demo-loopnet.toml)
    **{f"loopn_{m}_npib": Q(LOOP_N, f"methods/{m}/npib_mean") for m in ("realtime", "ideal", "shack_hartmann", "open")},
    **{f"loopn_{m}_gain": Q(LOOP_N, f"methods/{m}/gain") for m in ("realtime", "ideal", "shack_hartmann")},
    **{f"loopn_{m}_fade": Q(LOOP_N, f"methods/{m}/fades/probability") for m in ("realtime", "ideal", "open")},
    "loopn_realtime_delay": Q(LOOP_N, "methods/realtime/delay_frames", "{:.1f}"),
    "loopn_shack_hartmann_delay": Q(LOOP_N, "methods/shack_hartmann/delay_frames", "{:.1f}"),
    "loopn_rt_vs_ideal": Q(LOOP_N, "verdict/vs_ideal", "{:.2f}"),
    "loopn_rt_vs_sh": Q(LOOP_N, "verdict/vs_shack_hartmann", "{:.2f}"),
    # the demo loop with the real-time network of issue #51 (sensing/loop-demo-w48.toml): the headline
    **{f"loopw_{m}_npib": Q(LOOP_W, f"methods/{m}/npib_mean") for m in ("realtime", "ideal", "shack_hartmann", "open")},
    **{f"loopw_{m}_gain": Q(LOOP_W, f"methods/{m}/gain") for m in ("realtime", "ideal", "shack_hartmann")},
    **{f"loopw_{m}_fade": Q(LOOP_W, f"methods/{m}/fades/probability") for m in ("realtime", "ideal", "shack_hartmann", "open")},
    **{f"loopw_{m}_delay": Q(LOOP_W, f"methods/{m}/delay_frames", "{:.1f}") for m in ("realtime", "ideal", "shack_hartmann")},
    "loopw_rt_vs_ideal": Q(LOOP_W, "verdict/vs_ideal", "{:.2f}"),
    "loopw_rt_vs_sh": Q(LOOP_W, "verdict/vs_shack_hartmann", "{:.2f}"),
    **{f"loopw_psd_{m}_{b}": _loop_band(m, b, record=LOOP_W) for m in ("realtime", "ideal") for b in ("tt", "ho")},
    "loopw_realtime_residual": Q(LOOP_W, "methods/realtime/residual_rms_rad", "{:.1f}"),
    "loopw_open_tip_rms": D(lambda get: _modal_var(get(LOOP_W), "open", 2) ** 0.5, "{:.2f}"),
    # the same loop with the network's latency declared 0 (which latency would get it there)
    **{f"loopz_{m}_npib": Q(LOOP_Z, f"methods/{m}/npib_mean") for m in ("realtime", "ideal", "open")},
    **{f"loopz_{m}_gain": Q(LOOP_Z, f"methods/{m}/gain") for m in ("realtime", "ideal")},
    "loopz_realtime_delay": Q(LOOP_Z, "methods/realtime/delay_frames", "{:.2f}"),
    "loopz_rt_vs_ideal": Q(LOOP_Z, "verdict/vs_ideal", "{:.2f}"),
    # the same loop with the network's tip and tilt from the push-pull linear reconstructor (realtime_tt)
    **{f"loopt_{m}_npib": Q(LOOP_T, f"methods/{m}/npib_mean") for m in ("realtime_tt", "ideal", "shack_hartmann")},
    "loopt_realtime_tt_gain": Q(LOOP_T, "methods/realtime_tt/gain"),
    "loopt_realtime_tt_fade": Q(LOOP_T, "methods/realtime_tt/fades/probability"),
    "loopt_realtime_tt_latency_us": Q(LOOP_T, "methods/realtime_tt/latency_ms", "{:.0f}", 1e3),
    "loopt_rt_vs_ideal": Q(LOOP_T, "verdict/vs_ideal", "{:.2f}"),
    "loopt_rt_vs_sh": Q(LOOP_T, "verdict/vs_shack_hartmann", "{:.2f}"),
    **{f"loopt_psd_realtime_tt_{b}": _loop_band("realtime_tt", b, record=LOOP_T) for b in ("tt", "ho")},
    # the same loop with the network's tip and tilt from the in-focus channel's far-field peak (realtime_peak)
    "loopp_realtime_peak_npib": Q(LOOP_P, "methods/realtime_peak/npib_mean"),
    "loopp_realtime_peak_gain": Q(LOOP_P, "methods/realtime_peak/gain"),
    "loopp_realtime_peak_fade": Q(LOOP_P, "methods/realtime_peak/fades/probability"),
    "loopp_realtime_peak_latency_us": Q(LOOP_P, "methods/realtime_peak/latency_ms", "{:.0f}", 1e3),
    "loopp_rt_vs_ideal": Q(LOOP_P, "verdict/vs_ideal", "{:.2f}"),
    "loopp_rt_vs_sh": Q(LOOP_P, "verdict/vs_shack_hartmann", "{:.2f}"),
    # the same loops with the integrator's leak at 0.95 (sensing/loop-demo-w48-leak.toml): every gain searched
    **{f"loopk_{m}_npib": Q(LOOP_K, f"methods/{m}/npib_mean") for m in ("realtime", "ideal", "shack_hartmann", "open")},
    **{f"loopk_{m}_gain": Q(LOOP_K, f"methods/{m}/gain") for m in ("realtime", "ideal", "shack_hartmann")},
    **{f"loopk_{m}_fade": Q(LOOP_K, f"methods/{m}/fades/probability") for m in ("realtime", "ideal", "shack_hartmann", "open")},
    **{f"loopk_{m}_delay": Q(LOOP_K, f"methods/{m}/delay_frames", "{:.1f}") for m in ("realtime", "ideal", "shack_hartmann")},
    "loopk_rt_vs_ideal": Q(LOOP_K, "verdict/vs_ideal", "{:.2f}"),
    "loopk_rt_vs_sh": Q(LOOP_K, "verdict/vs_shack_hartmann", "{:.2f}"),
    # against the ideal loop at its better leak (0.95 here or 0.99 in the headline run)
    "loopk_rt_vs_best_ideal": D(lambda get: get(LOOP_K)["methods"]["realtime"]["npib_mean"] / max(
        get(LOOP_K)["methods"]["ideal"]["npib_mean"], get(LOOP_W)["methods"]["ideal"]["npib_mean"]), "{:.2f}"),
    **{f"loopk_psd_{m}_{b}": _loop_band(m, b, record=LOOP_K) for m in ("realtime", "ideal") for b in ("tt", "ho")},
    # its modal temporal spectra (docs/figures/loop_psd.py): power below 50 Hz over the open loop's; variances
    **{f"loopg_psd_{m}_{b}": _loop_band(m, b) for m in ("realtime", "ideal") for b in ("tt", "ho")},
    **{f"loopg_psd_{m}_var": _loop_band(m, "", None) for m in ("realtime", "ideal", "open")},
    # the map over rate x f_G x Rytov (sensing/loop-map-out/, metadesign loop-map loop-map)
    "map_rt_npib": Q(MAP, "verdict/npib_mean"),
    "map_ideal_npib": Q(MAP, "verdict/ideal_npib_mean"),
    "map_sh_npib": Q(MAP, "verdict/shack_hartmann_npib_mean"),
    "map_vs_ideal": Q(MAP, "verdict/vs_ideal", "{:.2f}"),
    "map_vs_sh": Q(MAP, "verdict/vs_shack_hartmann", "{:.0f}"),
    "map_delay": Q(MAP, "verdict/delay_frames", "{:.2f}"),
    **{f"map_scan_{i}": Q(MAP, f"verdict/latency_scan/npib_mean[{i}]") for i in range(5)},
    "map_min": Q(MAP, "seconds", "{:.0f}", 1 / 60),
    # the map with the headline's loops (sensing/loop-map-w48.toml: realtime-w48, leak 0.95, the searched gains)
    "mapw_rt_npib": Q(MAP_W, "verdict/npib_mean"),
    "mapw_ideal_npib": Q(MAP_W, "verdict/ideal_npib_mean"),
    "mapw_sh_npib": Q(MAP_W, "verdict/shack_hartmann_npib_mean"),
    "mapw_vs_ideal": Q(MAP_W, "verdict/vs_ideal", "{:.2f}"),
    "mapw_vs_sh": Q(MAP_W, "verdict/vs_shack_hartmann", "{:.2f}"),
    "mapw_delay": Q(MAP_W, "verdict/delay_frames", "{:.2f}"),
    **{f"mapw_scan_{i}": Q(MAP_W, f"verdict/latency_scan/npib_mean[{i}]") for i in range(5)},
    "mapw_min": Q(MAP_W, "seconds", "{:.0f}", 1 / 60),
    # the polarisation camera with and without retraining (sensing/polcam-demo/, sensing/polcam-retrained/)
    **{f"pc_unet_{k}": Q(PC, f"cameras/{c}/unet/captured_fraction") for k, c in _PC_CAMS.items()},
    **{f"pc_rt_{k}": Q(PC_RT, f"cameras/{c}/unet/captured_fraction") for k, c in _PC_CAMS.items()},
    "pc_rt_loss_ideal": D(lambda get: get(PC, "cameras/ideal/unet/captured_fraction")
                          - get(PC_RT, "cameras/ideal/unet/captured_fraction")),
}


def measured(repo: Path = REPO) -> dict[str, str]:
    """Every quoted number, formatted (name -> text); a missing record or key raises, naming it."""
    out = {}
    for name, q in MEASURED.items():
        try:
            v = q.value(repo)
        except (OSError, KeyError, IndexError, ValueError) as exc:
            where = q.file if isinstance(q, Q) else "a derived value"
            raise RuntimeError(f"measured result {name!r} ({where}): {exc}") from None
        if not math.isfinite(v):
            raise RuntimeError(f"measured result {name!r}: not finite ({v})")
        out[name] = q.fmt.format(v)
    return out


# ------------------------------------------------------------------ the {reproduce} role


def command_target(cmd: str, known) -> tuple[str, str] | None:
    """Where a reproduce command is documented: ("ref", its longest sub-command among ``known``, the
    CLI reference's sections) for ``metadesign ...``, ("doc", the benchmarks page) for
    ``python benchmarks/...``; None for anything else."""
    words = cmd.split()
    if words[:1] == ["metadesign"]:
        for n in range(len(words), 0, -1):
            if " ".join(words[:n]) in known:
                return "ref", " ".join(words[:n])
        return None
    if len(words) > 1 and words[0] == "python" and words[1].startswith("benchmarks/"):
        return "doc", "/guide/benchmarks"
    return None


@lru_cache(maxsize=1)
def _commands() -> frozenset:
    from cli_reference import command_helps

    return frozenset(name for name, _ in command_helps())


def reproduce_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    from docutils import nodes
    from docutils.utils import unescape
    from sphinx import addnodes

    cmd = unescape(text)
    lit = nodes.literal(cmd, cmd)
    target = command_target(cmd, _commands())
    if target is None:
        msg = inliner.reporter.warning(f"reproduce: no CLI reference or benchmark page for {cmd!r}", line=lineno)
        return [lit], [msg]
    kind, tgt = target
    if kind == "ref":
        tgt = nodes.make_id(tgt)  # the label cli_reference gives the command's section
    ref = addnodes.pending_xref(rawtext, refdomain="std", reftype=kind, reftarget=tgt, refexplicit=True,
                                refwarn=True)
    ref += lit
    return [ref], []


def setup(app):
    app.add_role("reproduce", reproduce_role)
    return {"version": "1", "parallel_read_safe": True}
