"""
Eight PSFs from the layout file (Fig. 2c)
=========================================

Stages 3 and 4 on the paper's 5 mm device: the design is written as an OASIS layout (51 million
pillars), read back exactly, and the as-fabricated forward model is built *from the layout file* (every
pillar's widths looked up in the library), then propagated to the camera: two frames (x- and
y-polarised), four spots each, eight defocus settings.  A 10 nm width bias shows what the fab does to
them.  (About a minute: the layout's write, read-back and design-rule check are most of it.)
"""

# %%
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from metadesign.design.recipe import load_design_recipe
from metadesign.design.store import run_design
from metadesign.layouts.make import make_layout
from metadesign.paths import repo_root
from metadesign.sensing.render import FabCases, fab_study, render_psf
from metadesign.turbulence.system import build_system

work = Path(tempfile.mkdtemp())
design, _ = run_design(load_design_recipe(repo_root() / "layouts" / "paper-5mm.toml"), work / "design")
made = make_layout(design, work / "design" / "layout.oas")
print(f"{made.write['pillars']:,} pillars, read-back exact: {made.verify['exact']}, "
      f"design rules passed: {made.drc['passed']}")

# %%
# The system factory: layout -> as-fabricated device -> sensor (a turbulence scenario would add the
# chain).  The two frames, each on its own colour scale (square root of the intensity over the frame's
# brightest pixel).  What to see: in each frame one or two spots are sharp and bright and the others
# spread into wide, dim patterns: the four lenses of a polarisation focus at four distances around the
# camera (48.8-51.6 mm against 50 mm), so each spot is defocused by its own amount: the diversity.
system = build_system(work / "design" / "layout.oas", repo_root() / "sensing" / "paper.toml")
res = render_psf(system.device, system.sensing)
fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), constrained_layout=True)
for ax, frame, name in zip(axes, res.frames, ("x-pol frame", "y-pol frame")):
    im = ax.imshow(np.sqrt(frame / frame.max()), cmap="magma", origin="upper", vmin=0, vmax=1)
    ax.set(title=name, xlabel="camera pixel", ylabel="camera pixel")
    fig.colorbar(im, ax=ax, label="sqrt(intensity / the frame's peak)")
fig.suptitle("The paper device's two sensor frames, a flat wavefront")

# %%
# The 8-channel tensor the reconstruction sees: each spot's quadrant area-resampled around its centre
# (here the central part of each), every channel on its own scale (colour bar: intensity over the
# channel's own peak) with its peak over the brightest channel's in the title.  What to see: eight
# different patterns, from a sharp spot (peak 1.00) to rings and grids of a few hundredths of its peak:
# the same wavefront seen through eight defocus settings is what lets the network tell its phase.
c = res.tensor.shape[-1] // 2
h = res.tensor.shape[-1] // 4
top = float(res.tensor.max())
fig, axes = plt.subplots(2, 4, figsize=(11, 5.6), constrained_layout=True)
for k, ax in enumerate(axes.flat):
    t = res.tensor[k, c - h:c + h, c - h:c + h]
    im = ax.imshow(t / t.max(), cmap="magma", vmin=0, vmax=1)
    ax.set_title(f"channel {k + 1} ({'xy'[k // 4]}-pol): peak {res.tensor[k].max() / top:.2f}", fontsize=9)
    ax.axis("off")
fig.colorbar(im, ax=axes, label="intensity / the channel's own peak", shrink=0.8)

# %%
# Fabrication: Strehl ratio and focusing efficiency of each channel for the nominal device and a +10 nm
# width bias (the bias costs about a tenth of the focused power and a little Strehl).
rows = fab_study(system.device, system.sensing, FabCases(bias_nm=(0.0, 10.0)))
for bias in (0.0, 10.0):
    s = [r["strehl"] for r in rows if r["bias_nm"] == bias]
    e = [100 * r["focusing_efficiency"] for r in rows if r["bias_nm"] == bias]
    print(f"bias {bias:+.0f} nm: Strehl {min(s):.3f}..{max(s):.3f}, focusing efficiency {min(e):.2f}..{max(e):.2f} %")
