"""
From eight spots to a correction (Fig. 3b)
==========================================

Stage 6: the committed demo U-Net (trained on the paper device's 8 x 64 x 64 tensors with 0-10 %
sensor noise) estimates the received phase from the eight PSFs; its conjugate is sent back through the
same turbulence and the power in the bucket (NPiB) is compared with no correction and with the phase
conjugate (the oracle).  Four beacons drawn here, from a seed no model was trained on.
"""

# %%
import matplotlib.pyplot as plt
import numpy as np
import torch

from metadesign.design.recipe import load_design_recipe
from metadesign.design.store import run_design
from metadesign.paths import repo_root
from metadesign.reconstruction.data import apply_noise
from metadesign.reconstruction.dataset import normalise_psf, received_crop
from metadesign.reconstruction.losses import PiB
from metadesign.reconstruction.model import load_model
from metadesign.sensing import AsFabricated
from metadesign.turbulence.system import build_system

torch.set_num_threads(1)
model, card = load_model(repo_root() / "sensing" / "models" / "demo-unet-robust.safetensors")
print("model trained on", card["dataset"]["path"], "- validated captured fraction:",
      round(card["metrics"]["val_captured_fraction"], 3))
design, _ = run_design(load_design_recipe(repo_root() / "layouts" / "paper-5mm.toml"))
chain = build_system(AsFabricated.from_design(design), repo_root() / "sensing" / "paper.toml",
                     repo_root() / "sensing" / "turbulence.toml", tensor_size=model.config.input_size).chain()
c0, a = received_crop(chain.turbulence.sc)
pib = PiB(chain.turbulence.sc, c0, a)

# %%
# Each beacon (columns): the 8-channel tensor with 5 % noise in (top: its first channel), the received
# phase the turbulence made (middle) and the U-Net's estimate of it (bottom), with the NPiB of its
# conjugate against no correction.  What to see: the estimate follows the large-scale shape of the
# received phase, not its fine structure or its branch points, and the corrected beam puts many times the
# uncorrected power in the bucket (the bottom titles).
fig, axes = plt.subplots(3, 4, figsize=(13, 9), constrained_layout=True)
for i, rytov in enumerate((0.3, 0.4, 0.5, 0.6)):
    seed = 90_000 + i
    s = chain.sample(seed, rytov)
    psf, _ = normalise_psf(s.tensor)
    x = torch.from_numpy(apply_noise(psf, np.random.default_rng(i), 5.0))[None]
    scr = torch.from_numpy(chain.at(rytov).screens(seed))[None]
    with torch.no_grad():
        phi = model(x)
        npib_unet = float(pib.npib_phase(phi, scr))
        npib_none = float(pib.npib_phase(torch.zeros_like(phi), scr))
    rec = s.received[c0:c0 + a, c0:c0 + a]
    mask = pib.ap.numpy().astype(bool)
    ch1 = x[0, 0].numpy()
    axes[0, i].imshow(ch1 / ch1.max(), cmap="magma", vmin=0, vmax=1)
    axes[0, i].set_title(f"Rytov {rytov}: channel 1 (5 % noise)", fontsize=9)
    axes[1, i].imshow(np.where(mask, np.angle(rec), np.nan), cmap="twilight", vmin=-np.pi, vmax=np.pi)
    axes[1, i].set_title("received phase (wrapped)", fontsize=9)
    axes[2, i].imshow(np.where(mask, np.angle(np.exp(1j * phi[0].numpy())), np.nan), cmap="twilight",
                      vmin=-np.pi, vmax=np.pi)
    axes[2, i].set_title(f"U-Net estimate: NPiB {npib_unet:.2f} (none {npib_none:.2f})", fontsize=9)
    for ax in axes[:, i]:
        ax.axis("off")
fig.colorbar(axes[0, 3].images[0], ax=axes[0, :], label="intensity / the channel's peak", shrink=0.9)
fig.colorbar(axes[1, 3].images[0], ax=axes[1:, :], label="phase (rad, wrapped)", shrink=0.9)
