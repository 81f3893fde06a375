"""
What the eight spots can tell: Fisher information of the diversity (co-design)
==============================================================================

Before training anything, the Fisher information of the sensor frame says how well *any* estimator can
determine each Zernike mode of the received wavefront: its inverse is the Cramer-Rao bound.  Here, on the
paper's 5 mm design (the device built from the atom map) with a plane wave at 1e6 photo-electrons per
frame: the paper's diversity (focal lengths 48.8-51.6 mm), the same sensor with all eight lenses focused
on the camera (no diversity), and a random diversity of the same parameter count (each channel's defocus
and Zernike terms 5-11, the space the co-design training searches).
"""

# %%
import matplotlib.pyplot as plt
import numpy as np
import torch

from metadesign.design.recipe import load_design_recipe
from metadesign.design.store import run_design
from metadesign.paths import repo_root
from metadesign.reconstruction.dataset import received_crop
from metadesign.sensing import AsFabricated, Device, ReceiverCrop, load_sensing_recipe
from metadesign.sensing.diversity import diversity_operators, focal_to_defocus, lens_table
from metadesign.sensing.fisher import crb, crop_zernike_basis, zernike_fisher
from metadesign.sensing.twin_diversity import DiversityTwin
from metadesign.turbulence import load_scenario

torch.set_num_threads(1)
design, _ = run_design(load_design_recipe(repo_root() / "layouts" / "paper-5mm.toml"))
sr = load_sensing_recipe(repo_root() / "sensing" / "paper.toml")
sc = load_scenario(repo_root() / "sensing" / "turbulence.toml")
pupil = AsFabricated.from_design(design).pupil(sr.sensor.distance, 64)  # a 64 x 64 coarse pupil: fast
dev = Device(pupil, sr.sensor, ReceiverCrop.of_scenario(sc, *received_crop(sc)))
ops = diversity_operators(dev.pupil, dev.sensor, lens_table(design.spec), dev.geometry)
twin = DiversityTwin(ops)
print("lenses (mm):", np.round(ops.f0 * 1e3, 2).tolist(), " camera at", sr.sensor.distance * 1e3, "mm")

# %%
# The Cramer-Rao bound of Noll modes 2 (tilt) to 15, for a unit plane wave on the receiver, with the
# frame normalised to a fixed sum (as the network sees it: the total flux tells it nothing).
c0, a, n_grid, dx, d2 = dev.geometry
basis = crop_zernike_basis(range(2, 16), c0, a, n_grid, dx, d2)
flat = (crop_zernike_basis([1], c0, a, n_grid, dx, d2)[0] != 0).astype(np.complex64)[None]


def bound(defocus_waves=None, zernike_rad=None):
    with torch.no_grad():
        twin.defocus_waves.zero_()
        twin.zernike_rad.zero_()
        if defocus_waves is not None:
            twin.defocus_waves.copy_(torch.as_tensor(defocus_waves))
        if zernike_rad is not None:
            twin.zernike_rad.copy_(torch.as_tensor(zernike_rad))
    return crb(zernike_fisher(twin, flat, basis, 1e6, normalise_sum=True)[0])


focused = focal_to_defocus(sr.sensor.distance, ops.f0, ops.wavelength, ops.radius)
rng = np.random.default_rng(0)
curves = {"paper's diversity": bound(),
          "no diversity (all lenses focused on the camera)": bound(focused),
          "a random diversity (defocus 0.5 waves, Zernike 0.5 rad rms)":
              bound(rng.normal(0, 0.5, (2, 4)), rng.normal(0, 0.5, (2, 4, len(ops.modes))))}
fig, ax = plt.subplots(figsize=(8, 4.6), constrained_layout=True)
for name, v in curves.items():
    j = np.arange(2, 2 + len(v))
    ok = np.isfinite(v)
    ax.semilogy(j[ok], np.sqrt(v[ok]), "o-", label=name)
    print(f"{name}: rms bound over modes 2-15 {np.sqrt(np.mean(v[ok])):.2e} rad"
          + ("" if ok.all() else f" ({int((~ok).sum())} modes unseen)"))
ax.set(xlabel="Zernike mode of the received wavefront (Noll)", ylabel="Cramer-Rao bound, rms (rad)",
       title="Plane wave, 1e6 photo-electrons per frame")
ax.grid(True, which="both", alpha=0.3)
ax.legend(fontsize=8)
