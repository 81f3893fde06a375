"""Reading a dataset: :class:`PSFDataset`, a ``torch.utils.data.Dataset`` over a metadesign dataset store
(the store itself, its format, build, checks and device: :mod:`.dataset`).  It opens the zarr arrays
lazily in each DataLoader worker, checks every sample it reads (a damaged one is one line naming its
shard), applies the noise when samples are read (seeded per sample and epoch, so one dataset serves
every noise study), and returns tensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..turbulence.propagate import Turbulence
from ..validation import ValidationError, check_int, check_number
from .dataset import check_psf, damaged, has_operators, load_device, open_dataset, sample_rytov

__all__ = ["PSFDataset", "apply_noise"]


def apply_noise(psf: np.ndarray, rng: np.random.Generator, gaussian_percent: float = 0.0,
                photons_at_peak: float | None = None, read_noise_e: float = 0.0) -> np.ndarray:
    """Noise on an (8, S, S) normalised PSF tensor, each channel scaled by its own peak (the camera's
    exposure is set on the brightest spot): shot noise with ``photons_at_peak`` photo-electrons at the
    peak plus Gaussian read noise (electrons), then additive Gaussian noise of ``gaussian_percent`` % of
    the peak (the paper's noise levels, Fig. 3c-d)."""
    x = np.asarray(psf, np.float64)
    peak = x.max(axis=(-2, -1), keepdims=True)
    peak = np.where(peak > 0, peak, 1.0)
    y = np.clip(x / peak, 0.0, None)
    if photons_at_peak:
        e = rng.poisson(y * photons_at_peak).astype(np.float64)
        if read_noise_e:
            e += rng.normal(0.0, read_noise_e, e.shape)
        y = e / photons_at_peak
    if gaussian_percent:
        y = y + rng.normal(0.0, gaussian_percent / 100.0, y.shape)
    return (y * peak).astype(np.float32)


class PSFDataset:
    """Samples of one split: ``{"psf": (8,S,S) float32, "received": (A,A) complex64, "rytov", "rytov_measured",
    "seed", "index"}`` as torch tensors, plus ``"screens"`` (regenerated) and ``"A"`` (the stored bucket
    operator) when asked.  Works with ``DataLoader(num_workers > 0)``: nothing but small
    metadata is read in the constructor; each worker opens the store on first use."""

    def __init__(self, path: str | Path, split: str = "train", gaussian_percent: float = 0.0,
                 photons_at_peak: float | None = None, read_noise_e: float = 0.0, noise_seed: int = 0,
                 limit: int | None = None, screens: bool = False, operators: bool = False):
        if split not in ("train", "val", "test", "all"):
            raise ValidationError(f"split: expected train, val, test or all, got {split!r}")
        check_number("gaussian_percent", gaussian_percent, 0, 100)
        if photons_at_peak is not None:
            check_number("photons_at_peak", photons_at_peak, 0, 1e15, open_lo=True)
        check_number("read_noise_e", read_noise_e, 0, 1e6)
        check_int("noise_seed", noise_seed, 0, 2**63 - 1)
        self.info = open_dataset(path)
        self.path = str(path)
        self.idx = self.info.indices(split)
        if limit is not None:
            self.idx = self.idx[:limit]
        self.noise = (gaussian_percent, photons_at_peak, read_noise_e)
        self.noise_seed = noise_seed
        self.epoch = 0
        self.screens = screens  # regenerate each sample's screens (the end-to-end loss needs them)
        self.operators = operators  # load each sample's stored bucket operator ("A": dataset operators)
        if operators:
            self.require_operators(split)
        self._g = None
        self._tb = None

    def require_operators(self, split: str) -> None:
        if not has_operators(self.info.attrs, split):
            raise ValidationError(f"{self.path}: no stored bucket operators for the {split} split "
                                  f"(run `metadesign dataset operators {self.path} --splits {split}`)")

    def scenario(self):
        """The turbulence scenario the dataset was made with (from its provenance)."""
        return self.info.scenario()

    def crop(self) -> tuple[int, int]:
        return self.info.crop()

    def device(self):
        """The device the dataset was made with (:func:`~.dataset.load_device`)."""
        return load_device(self.path)

    def exact_rytov(self, i: int) -> float:
        """The float64 Rytov number sample ``i`` was made with (stored as float32), from the root seed."""
        r = self.info.attrs["rytov"]
        return sample_rytov(int(self.info.attrs["root_seed"]), i, tuple(r["range"]), r["values"])

    def screens_of(self, i: int) -> np.ndarray:
        """The 13 screens of sample ``i``, regenerated bit for bit from its seed.  Captured data
        (``propagation = "slm"``): vacuum screens with the SLM phase as the receiver-plane (last) screen."""
        if self.info.attrs.get("propagation") == "slm":
            sc = self.scenario()
            c0, a = self.crop()
            out = np.zeros((sc.n_screens, sc.n_grid, sc.n_grid), np.float32)
            try:
                rec = np.asarray(self._arrays()["received"][i])
            except Exception as exc:
                raise damaged(self.path, i, self.info.attrs["shard_size"], exc) from None
            out[-1, c0:c0 + a, c0:c0 + a] = np.where(np.abs(rec) > 0, np.angle(rec), 0)
            return out
        if self._tb is None:
            self._tb = Turbulence(self.scenario(), check=False)
        return self._tb.at_rytov(self.exact_rytov(i), check=False).screens(int(self.info.seed[i]))

    def set_epoch(self, epoch: int) -> None:
        """A new noise draw per epoch (same epoch, same bytes)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.idx)

    def _arrays(self) -> dict:
        """The store's arrays by name, opened once per process (a group look-up costs ~0.5 ms: a tenth
        of a sample's load)."""
        if self._g is None:
            import zarr

            g = zarr.open_group(self.path, mode="r")
            self._g = {k: g[k] for k in ("psf", "received", *(("pib_operator",) if "pib_operator" in g else ()))}
        return self._g

    def __getstate__(self):  # DataLoader workers re-open the store themselves
        d = dict(self.__dict__)
        d["_g"] = None
        d["_tb"] = None
        return d

    def get(self, j: int) -> dict:
        """Sample ``j`` of this split as numpy arrays."""
        i = int(self.idx[j])
        g = self._arrays()
        try:
            psf = np.asarray(g["psf"][i])
            received = np.asarray(g["received"][i])
        except Exception as exc:  # a truncated shard or a damaged chunk: zarr/numcodecs raise many kinds
            raise damaged(self.path, i, self.info.attrs["shard_size"], exc) from None
        why = check_psf(psf) or (None if np.isfinite(received).all() else "non-finite received field")
        if why:
            raise damaged(self.path, i, self.info.attrs["shard_size"], why)
        if any(self.noise[:2]):
            rng = np.random.default_rng(np.random.SeedSequence(self.noise_seed, spawn_key=(self.epoch, i)))
            psf = apply_noise(psf, rng, *self.noise)
        out = {"psf": psf, "received": received, "rytov": float(self.info.rytov[i]),
               "rytov_measured": float(self.info.rytov_measured[i]), "seed": int(self.info.seed[i]), "index": i}
        if self.screens:
            out["screens"] = self.screens_of(i)
        if self.operators:
            try:
                out["A"] = np.asarray(g["pib_operator"][i])
            except Exception as exc:
                raise damaged(self.path, i, self.info.attrs["shard_size"], exc) from None
            if not out["A"].any():  # the fill value: a shard file lost after the operators were finished
                raise ValidationError(f"{self.path}: sample {i} has no stored bucket operator (damaged store: "
                                      "rerun `metadesign dataset operators --overwrite`)")
        return out

    def __getitem__(self, j: int) -> dict:
        import torch

        s = self.get(j)
        return {"psf": torch.from_numpy(s["psf"]), "received": torch.from_numpy(s["received"]),
                "rytov": torch.tensor(s["rytov"], dtype=torch.float32),
                "rytov_measured": torch.tensor(s["rytov_measured"], dtype=torch.float32),
                "seed": torch.tensor(s["seed"], dtype=torch.int64), "index": torch.tensor(s["index"]),
                **({"screens": torch.from_numpy(s["screens"])} if "screens" in s else {}),
                **({"A": torch.from_numpy(s["A"])} if "A" in s else {})}
