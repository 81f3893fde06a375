"""Stage 6: reconstruction.  Datasets of 8-PSF frames (``dataset``), their torch
loader (``data``); the U-Net, its training and evaluation follow."""

from .data import PSFDataset, apply_noise
from .dataset import DatasetRecipe, build_dataset, load_dataset_recipe, open_dataset

__all__ = ["PSFDataset", "apply_noise", "DatasetRecipe", "build_dataset", "load_dataset_recipe", "open_dataset"]
