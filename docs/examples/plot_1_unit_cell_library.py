"""
The unit-cell library (Fig. S1)
===============================

Stage 1 solves every rectangular a-Si pillar (widths ``wx`` x ``wy``, height 1.2 um, period 0.7 um, on
fused silica at 1550 nm) with RCWA for both polarisations.  The committed table
``library/paper.npz`` is what every later stage looks atoms up in.  Here: its phase and transmission
for x- and y-polarised light, and one cell re-solved against the table.
"""

# %%
import matplotlib.pyplot as plt
import numpy as np

from metadesign.library import SolverSettings, Stack, load_library, solve_cell
from metadesign.paths import default_library_path

lib = load_library(default_library_path())
print(lib.summary()["grid"], "widths", lib.wx[0] * 1e9, "..", lib.wx[-1] * 1e9, "nm")

# %%
# Phase and transmission against the two widths.  Birefringence is what the design uses: a pillar
# wider in x delays x-polarised light more, so one pillar can hold two independent phases.
ext = [lib.wx[0] * 1e6, lib.wx[-1] * 1e6, lib.wy[0] * 1e6, lib.wy[-1] * 1e6]
fig, axes = plt.subplots(2, 2, figsize=(9, 7.5), constrained_layout=True)
for r, (name, t) in enumerate((("x-pol", lib.t_x), ("y-pol", lib.t_y))):
    im = axes[r, 0].imshow(np.angle(t).T, origin="lower", extent=ext, cmap="twilight", vmin=-np.pi, vmax=np.pi)
    fig.colorbar(im, ax=axes[r, 0], label="phase (rad)")
    im = axes[r, 1].imshow(np.abs(t).T ** 2, origin="lower", extent=ext, cmap="viridis", vmin=0, vmax=1)
    fig.colorbar(im, ax=axes[r, 1], label="|t|^2")
    for ax in axes[r]:
        ax.set(xlabel="wx (um)", ylabel="wy (um)", title=f"{name}")
fig.suptitle("Unit-cell library: phase and zero-order transmission")

# %%
# The table is checked, not trusted: one cell solved again with the same stack and truncation.
st = lib.meta["stack"]
stack = Stack(st["wavelength_m"], st["period_m"], st["height_m"], st["n_pillar"], st["n_substrate"],
              st["n_superstrate"])
cell = solve_cell(lib.wx[40], lib.wy[20], stack, SolverSettings(lib.meta["solver"]["n_harmonics_requested"]))
print("max |jones - table| =", float(np.abs(cell.jones - lib.jones[40, 20]).max()))
