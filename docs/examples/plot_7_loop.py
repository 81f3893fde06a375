"""
The loop in time: a closed adaptive-optics loop on moving turbulence
====================================================================

The loop of ``metadesign loop`` (:doc:`the loop guide </guide/loop>`) on a small path that runs in seconds:
a beacon through five frozen-flow screens moving at 20 m/s (1 km, weak turbulence, 128 x 128 samples),
a Gaussian deformable mirror with 8 actuators across the 10 cm receiver, and a leaky integrator with two
frames of delay (one frame corrected on the next, plus one frame of read-out) at 2 kHz.  The sensor is
the ideal one (the residual's phase, no latency): what the loop can do at best with this mirror and this
delay.  The same turbulence runs open, closed at two gains, and through the zero-delay mirror-fitted
oracle (the mirror fitted to the true phase at each instant: only the fitting error left).
"""

# %%
import matplotlib.pyplot as plt
import numpy as np

from metadesign.optics.control import Controller, closed_loop_bandwidth, closed_loop_stable, rejection_tf
from metadesign.optics.dm import DeformableMirror, ModalDM
from metadesign.reconstruction.dataset import received_crop
from metadesign.reconstruction.losses import PiB
from metadesign.sensing.device import ReceiverCrop
from metadesign.studies.loop import IdealPhaseSensor, LoopTiming, LoopWorld, run_loop
from metadesign.studies.loop_stats import rejection_measured, welch_psd
from metadesign.turbulence.frozen import FrozenFlow
from metadesign.turbulence.propagate import Turbulence
from metadesign.turbulence.scenario import scenario_from_dict
from metadesign.turbulence.temporal import Wind, temporal_summary

FS, STEPS, SPEED, GAINS = 2000.0, 768, 20.0, (0.3, 0.6)
sc = scenario_from_dict({"path": {"n_screens": 5, "rytov": 0.025, "length_m": 1000.0, "inner_scale_cm": 0.1},
                         "grid": {"n": 128, "spacing_mm": 2.5}, "receiver": {"aperture_cm": 10.0}})
tb = Turbulence(sc, check=False)
wind = Wind.from_speeds([SPEED] * sc.n_screens)
c0, a = received_crop(sc)
# the loop's clock: one exposure instant per frame (the discrete model's own timing), one frame of read-out
timing = LoopTiming(FS, substeps=1, readout_frames=1.0)
flow = FrozenFlow(tb.grid, tb.path.r0_screens, wind, timing.dt / timing.substeps, STEPS * timing.substeps, seed=1)
world = LoopWorld(tb, flow.screens, c0, a, PiB(sc, c0, a))
crop = ReceiverCrop.of_scenario(sc, c0, a)
dm = DeformableMirror.for_crop(crop, n_act=8, coupling=0.15, regularisation=1e-4)
modes = np.asarray(ModalDM.for_crop(crop, n_modes=10).influence, np.float64)  # Noll 2..11: the spectra's basis
tw = temporal_summary(sc, wind)
print(f"f_G {tw['greenwood_hz']:.0f} Hz (plane wave), tau0 {tw['tau0_s'] * 1e3:.2f} ms; "
      f"{dm.n} actuators; delay {timing.delay_frames:g} frames at {FS:.0f} Hz")

runs = {"open loop": run_loop(world, timing, STEPS, "open", modes=modes),
        "mirror-fitted oracle, no delay": run_loop(world, timing, STEPS, "fitted", dm=dm)}
for g in GAINS:
    runs[f"ideal sensor, gain {g}"] = run_loop(world, timing, STEPS, "ideal", IdealPhaseSensor(), dm,
                                              Controller(g, timing.delay_frames), modes=modes)
    print(f"gain {g}: stable {closed_loop_stable(g, timing.delay_frames)}, -3 dB closed-loop bandwidth "
          f"{closed_loop_bandwidth(FS, g, timing.delay_frames):.0f} Hz")
print("gain 1 with two frames of delay: stable", closed_loop_stable(1.0, timing.delay_frames))
for name, r in runs.items():
    print(f"{name:32s} mean NPiB {r['npib'][64:].mean():.3f}, residual {r['residual_rms'][64:].mean():.2f} rad rms")

# %%
# The power in the bucket of the corrected outgoing beam at every frame, through the turbulence of that
# instant.  What to see: both closed loops hold the NPiB above the open loop's (its deep fades are gone),
# but below the zero-delay oracle's, which leaves only the mirror's fitting error (its residual rms,
# printed above): the gap is the servo lag, the turbulence moving on during the two frames the correction
# is late.  The higher gain is not better: with two frames of delay it amplifies the turbulence at a few
# hundred hertz (below).
t_ms = np.arange(STEPS) / FS * 1e3
fig, ax = plt.subplots(figsize=(8, 3.8), constrained_layout=True)
for name, r in runs.items():
    ax.plot(t_ms, r["npib"], lw=1, label=name)
ax.set(xlabel="time (ms)", ylabel="NPiB", ylim=(0, 1.1), title=f"{FS:.0f} Hz loop, f_G {tw['greenwood_hz']:.0f} Hz")
ax.legend(fontsize=8, loc="lower right")

# %%
# The residual's temporal spectra (Welch, 128-frame segments, the first 64 frames dropped; the 10 Zernike
# modes' power summed) and the rejection they measure, closed over open loop on the same turbulence,
# against the theory ``|1 / (1 + H_OL)|^2`` of the integrator with its delay
# (:func:`metadesign.optics.control.rejection_tf`; ``H_OL = g z^-2 / (1 - z^-1)`` here).  What to see:
# at the lowest frequencies the loop removes some 15-20 dB of the turbulence's power; the overshoot above
# 0 dB, where the delay turns the correction's phase around, grows with the gain, and the measurement
# follows the theory through it, within about 2 dB up to just under ``fs / 4`` (dotted; this short run:
# 10 Welch segments).  Beyond that both spectra lie some 30 dB under their low-frequency level and the
# measured ratio falls below the theory (``tests/test_loop_theory.py`` checks a longer run against the
# same theory up to ``fs / 8``).
fig, axs = plt.subplots(1, 2, figsize=(12, 4.2), constrained_layout=True)
f, p_open = welch_psd(runs["open loop"]["modal"][64:], FS, segment=128)
axs[0].loglog(f[1:], p_open.sum(axis=1)[1:], "k", label="open loop")
for g in GAINS:
    r = runs[f"ideal sensor, gain {g}"]
    _, p = welch_psd(r["modal"][64:], FS, segment=128)
    line, = axs[0].loglog(f[1:], p.sum(axis=1)[1:], label=f"closed, gain {g}")
    fm, rtf = rejection_measured(r["modal"][64:], runs["open loop"]["modal"][64:], FS, segment=128)
    th = np.abs(rejection_tf(fm[1:], FS, g, timing.delay_frames)) ** 2
    axs[1].semilogx(fm[1:], 10 * np.log10(rtf[1:]), color=line.get_color(), label=f"measured, gain {g}")
    axs[1].semilogx(fm[1:], 10 * np.log10(th), "--", color=line.get_color(), label=f"1 / (1 + H_OL), gain {g}")
axs[0].set(xlabel="f (Hz)", ylabel="PSD, Noll 2-11 summed (rad^2 / Hz)", title="modal temporal spectra")
axs[0].legend(fontsize=8)
axs[1].axvline(FS / 4, color="0.6", lw=0.8, ls=":")
axs[1].axhline(0, color="0.6", lw=0.8)
axs[1].set(xlabel="f (Hz)", ylabel="|RTF|^2 (dB)",
           title=f"rejection, {timing.delay_frames:g} frames of delay (dotted: fs / 4)")
axs[1].legend(fontsize=8, loc="lower right")
