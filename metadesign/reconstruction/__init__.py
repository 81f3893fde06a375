"""Stage 6: reconstruction.  Datasets of 8-PSF tensors and their store (:mod:`.dataset`: build, open,
verify, the device a dataset was made with), the torch loader over a store (:mod:`.data`), the U-Net
(:mod:`.model`), the losses (:mod:`.losses`: the end-to-end power in bucket), training (:mod:`.train`),
evaluation (:mod:`.evaluate`, :mod:`.metrics`), ONNX export (:mod:`.export`), the stored bucket operators
(:mod:`.operators`), capture import (:mod:`.captures`), the model-based baselines (:mod:`.retrieval`,
:mod:`.shack_hartmann`) and every wavefront estimator behind one interface (:mod:`.estimators`)."""

from .captures import ImportOptions, import_captures
from .data import PSFDataset, apply_noise
from .dataset import (
    DatasetRecipe,
    build_dataset,
    load_dataset_recipe,
    load_device,
    open_dataset,
    verify_dataset,
)
from .estimators import ESTIMATORS, Estimator, make_estimator, register
from .evaluate import evaluate_model
from .export import export_onnx
from .losses import LOSSES, PiB
from .metrics import captured_fraction
from .model import UNetConfig, build_unet, load_model, save_model
from .operators import build_operators
from .train import TrainRecipe, load_train_recipe, train

__all__ = ["ImportOptions", "import_captures", "PSFDataset", "apply_noise", "DatasetRecipe", "build_dataset",
           "load_dataset_recipe", "load_device", "open_dataset", "verify_dataset", "ESTIMATORS", "Estimator",
           "make_estimator", "register", "evaluate_model", "export_onnx", "LOSSES", "PiB", "captured_fraction",
           "UNetConfig", "build_unet", "load_model", "save_model", "build_operators", "TrainRecipe",
           "load_train_recipe", "train"]
