"""
Turbulence: screens against theory, and a beacon on the sensor (Figs. S5, S6)
==============================================================================

Stage 5: modified von Karman phase screens (with subharmonics) on a split-step path whose screen
strengths are solved for a target Rytov number.  The screens' structure function is checked against
the theory of the same spectrum, and one scintillated beacon goes through the paper's device onto the
sensor: what the reconstruction has to invert.
"""

# %%
import matplotlib.pyplot as plt
import numpy as np

from metadesign.design.recipe import load_design_recipe
from metadesign.design.store import run_design
from metadesign.paths import repo_root
from metadesign.sensing import AsFabricated
from metadesign.turbulence import load_scenario
from metadesign.turbulence.system import build_system
from metadesign.turbulence.validate import structure_function_check

sc = load_scenario(repo_root() / "sensing" / "turbulence.toml")
sf = structure_function_check(sc, n_screens=60, seed=0)
fig, ax = plt.subplots(figsize=(5.5, 4), constrained_layout=True)
ax.loglog(np.array(sf["r_m"]) * 1e3, sf["theory"], "k-", label="theory (same PSD)")
ax.loglog(np.array(sf["r_m"]) * 1e3, sf["measured"], "o", label="60 screens")
ax.set(xlabel="separation (mm)", ylabel="phase structure function (rad^2)", title="MvK screens, r0 = 5 cm")
ax.legend()
print("measured / theory:", np.round(sf["ratio"], 3))

# %%
# A beacon at Rytov 0.5 through the paper's 5 mm design (the design, not the layout file: the device
# is built from the atom map directly, the way the demo's stage 6 does).  What to see: the received
# amplitude is patchy (scintillation: bright and dark regions across the aperture), the phase wraps
# across the aperture, and where the amplitude nearly vanishes (blank) it can wind around the dark spot
# (a branch point); on the sensor the spots of the flat wavefront (previous example) have broken into
# speckled patterns that differ from spot to spot.
design, _ = run_design(load_design_recipe(repo_root() / "layouts" / "paper-5mm.toml"))
chain = build_system(AsFabricated.from_design(design), repo_root() / "sensing" / "paper.toml", sc).chain()
smp = chain.sample(seed=3, rytov=0.5)
a = np.abs(smp.e_in)
fig, axes = plt.subplots(1, 3, figsize=(14, 4.2), constrained_layout=True)
im = axes[0].imshow(a / a.max(), cmap="gray", vmin=0, vmax=1)
fig.colorbar(im, ax=axes[0], label="amplitude / its maximum", shrink=0.85)
axes[0].set_title("received amplitude on the metasurface")
im = axes[1].imshow(np.where(a > 0.05 * a.max(), np.angle(smp.e_in), np.nan), cmap="twilight",
                    vmin=-np.pi, vmax=np.pi)
fig.colorbar(im, ax=axes[1], label="phase (rad, wrapped)", shrink=0.85)
axes[1].set_title("received phase (wrapped; blank where the amplitude < 5 %)")
im = axes[2].imshow(np.sqrt(smp.frames[0] / smp.frames[0].max()), cmap="magma", vmin=0, vmax=1)
fig.colorbar(im, ax=axes[2], label="sqrt(intensity / the frame's peak)", shrink=0.85)
axes[2].set_title("x-pol sensor frame")
for ax in axes:
    ax.axis("off")
