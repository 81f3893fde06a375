"""
Eq. 1 lenses, binned and mapped onto atoms (Fig. S2)
====================================================

Stage 2: each of the eight channels is an off-axis lens (Eq. 1); the x- and y-polarised phases of a
2 x 2 supercell interleave four lenses per polarisation.  The discretizer bins the target phases into
16 x 16 birefringent bins and maps each bin onto its nearest library atom.  This example builds the
embedded demo design (a 0.5 mm aperture, same lenses scaled) and shows target, realised phase and error.
"""

# %%
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from metadesign.design.recipe import load_design_recipe
from metadesign.design.store import run_design
from metadesign.paths import repo_root

recipe = load_design_recipe(repo_root() / "layouts" / "demo.toml")
work = Path(tempfile.mkdtemp())
design, path = run_design(recipe, work / "design")
m = design.metrics
print(f"{design.spec.n_cells} x {design.spec.n_cells} cells, {m['n_atoms']} atoms, "
      f"RMSE x {m['rmse_rad'][0]:.3f} rad, y {m['rmse_rad'][1]:.3f} rad")

# %%
# The lens table: the four lenses of each polarisation (focal length, where the spot lands).
spec = design.spec
for pol, chans in (("x", spec.channels_x), ("y", spec.channels_y)):
    for k, ch in enumerate(chans, 1):
        print(f"{pol}-pol lens {k}: f = {ch.focal_length * 1e3:.2f} mm, "
              f"offset ({ch.offset_x * 1e6:+.0f}, {ch.offset_y * 1e6:+.0f}) um")

# %%
# Target phase (Eq. 1, four interleaved lenses) and the phase the mapped atoms realise, in a corner of
# the aperture where the pillars' 2 x 2 interleave shows.  The error comes from the 16 x 16 binning
# (half a bin: pi/16) and from mapping each bin onto the nearest atom the library can make, which need
# not sit at the bin's centre (cells below the transmission threshold are not used).
from metadesign.design.phase import design_phase

n = 48
idx = np.arange(n)
fig, axes = plt.subplots(2, 3, figsize=(12, 7.5), constrained_layout=True)
for r, pol in enumerate((0, 1)):
    target = design_phase(spec, pol, idx, idx, offset=design.offsets[pol])
    realised = design.atoms.phase[design.index_map[:n, :n], pol]
    err = np.angle(np.exp(1j * (realised - target)))
    for ax, img, title, cmap, lim in ((axes[r, 0], target, "target", "twilight", np.pi),
                                       (axes[r, 1], realised, "realised by the atoms", "twilight", np.pi),
                                       (axes[r, 2], err, "error", "RdBu_r", 2 * np.pi / 16)):
        im = ax.imshow(img, cmap=cmap, vmin=-lim, vmax=lim, origin="lower")
        ax.set(title=f"{'xy'[pol]}-pol: {title}", xlabel="cell", ylabel="cell")
        fig.colorbar(im, ax=ax, label="rad")
print("peak error (rad):", m["peak_error_rad"], " half a bin:", np.pi / 16)
