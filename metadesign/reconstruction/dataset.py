"""Stage 6a, datasets of 8-PSF frames from scintillated beacons through the as-fabricated metasurface:
one name for the three modules that hold them,

* :mod:`.dataset_recipe`: the recipe (its TOML tables parsed and checked; the seed, Rytov number and split
  the recipe decides for each sample),
* :mod:`.dataset_build`: the build (the samples, the shards, the run over local workers or a Dask cluster,
  resumable after SIGKILL),
* :mod:`.dataset_store`: the zarr v3 store (its layout, created, opened, verified, asked for its device).

Reading samples for training and evaluation: :mod:`.data`.
"""

from __future__ import annotations

from .dataset_build import (ShardContext, _build_dataset, _device_pupil, _make_shard, build_dataset,
                            ensure_layout, make_sample, make_shard, measured_rytov, normalise_psf, run_shards,
                            shard_folder, shard_name)
from .dataset_recipe import (_MAX_SEED, SECTIONS, TENSOR_SIZE, DatasetRecipe, dataset_recipe_from_dict,
                             expected_sizes, load_dataset_recipe, received_crop, sample_rytov, sample_seed,
                             split_labels)
from .dataset_store import (_ARRAYS, CF_ATTRS, DATASET_FORMAT, JSON_ATTRS, OPERATOR_ARRAY, PSF_SUM_TOL, PUPIL_GROUP,
                            SAMPLE_COORDINATES, DatasetInfo, _write_coordinates, check_psf, consolidate, create_store,
                            damaged, decoded_attrs, has_operators, load_device, mark_complete, open_dataset,
                            open_store, open_xarray, operator_info, read_attrs, read_store_pupil, store_attrs,
                            verify_dataset, write_store_pupil)

_create_store = create_store  # the names the module had before its split
_read_attrs = read_attrs

__all__ = ["open_xarray", "open_store", "DatasetRecipe", "load_dataset_recipe", "dataset_recipe_from_dict", "build_dataset", "open_dataset",
           "DatasetInfo", "DATASET_FORMAT", "sample_seed", "sample_rytov", "make_sample", "ShardContext",
           "received_crop", "measured_rytov", "normalise_psf", "load_device", "expected_sizes", "verify_dataset", "check_psf", "damaged",
           "read_attrs", "decoded_attrs", "store_attrs", "mark_complete", "JSON_ATTRS"]
