"""Packaging of the committed products the demo and the default recipes need (metadata: pyproject.toml).

The unit-cell libraries, the recipes and the demo models live in ``library/``, ``layouts/`` and ``sensing/``
at the top of the checkout; a wheel carries them as ``metadesign/products/{library,layouts,sensing}``, so
``pip install .`` then ``metadesign demo`` works from any folder (``metadesign.paths`` finds them in either
place)."""

from setuptools import find_packages, setup

PRODUCTS = {
    "metadesign.products.library": ("library", ["paper.npz", "paper.toml", "paper-fab.npz", "paper-fab.toml",
                                                "paper-supercells.toml", "paper-coupling.safetensors",
                                                "paper-coupling.safetensors.json"]),
    "metadesign.products.layouts": ("layouts", ["*.toml"]),
    "metadesign.products.sensing": ("sensing", ["*.toml"]),
    # the demo's robust U-Net and its learned refinement (which names the U-Net beside it), and the
    # 5 %-noise model the README's examples load
    "metadesign.products.sensing.models": ("sensing/models", ["demo-unet-robust.safetensors",
                                                              "demo-unet-robust.safetensors.json",
                                                              "demo-refine.safetensors", "demo-refine.safetensors.json",
                                                              "demo-unet-long.safetensors",
                                                              "demo-unet-long.safetensors.json"]),
}

setup(
    packages=find_packages(include=["metadesign", "metadesign.*"]) + list(PRODUCTS),
    package_dir={name: folder for name, (folder, _) in PRODUCTS.items()},
    package_data={name: files for name, (_, files) in PRODUCTS.items()},
    include_package_data=False,
)
