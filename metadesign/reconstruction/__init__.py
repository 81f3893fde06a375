"""Stage 6: reconstruction.  Datasets of 8-PSF tensors (:mod:`.dataset`: the recipe
:mod:`.dataset_recipe`, the build :mod:`.dataset_build`, the store :mod:`.dataset_store`: open, verify, the
device a dataset was made with), the torch loader over a store (:mod:`.data`), the U-Net
(:mod:`.model`), the losses (:mod:`.losses`: the end-to-end power in bucket), training (:mod:`.train`),
evaluation (:mod:`.evaluate`, :mod:`.metrics`), ONNX export (:mod:`.export`), the stored bucket operators
(:mod:`.operators`), capture import (:mod:`.captures`), the model-based baselines (:mod:`.retrieval`,
:mod:`.shack_hartmann`) and every wavefront estimator behind one interface (:mod:`.estimators`)."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562); a function named like its
#: module (``train.train``) is reached through the module
_EXPORTS = {
    "ImportOptions": "captures", "import_captures": "captures", "PSFDataset": "data", "apply_noise": "data",
    "DatasetRecipe": "dataset", "build_dataset": "dataset", "load_dataset_recipe": "dataset",
    "load_device": "dataset", "open_dataset": "dataset", "verify_dataset": "dataset", "ESTIMATORS": "estimators",
    "Estimator": "estimators", "make_estimator": "estimators", "register": "estimators",
    "evaluate_model": "evaluate", "export_onnx": "export", "LOSSES": "losses", "PiB": "losses",
    "captured_fraction": "metrics", "UNetConfig": "model", "build_unet": "model", "load_model": "model",
    "save_model": "model", "build_operators": "operators", "TrainRecipe": "train", "load_train_recipe": "train",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

