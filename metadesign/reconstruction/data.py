"""Reading a dataset: :class:`PSFDataset`, a ``torch.utils.data.Dataset`` over a metadesign dataset store
(the store itself, its format, checks and device: :mod:`.dataset_store`).  It opens the zarr arrays
lazily in each DataLoader worker, checks every sample it reads (a damaged one is one line naming its
shard), applies the noise when samples are read (seeded per sample and epoch, so one dataset serves
every noise study), and returns tensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..turbulence.propagate import Turbulence
from ..validation import ValidationError, check_int, check_number
from ..sensing.sensor import NoiseSpec, add_noise
from .dataset_recipe import sample_rytov
from .dataset_store import check_psf, damaged, has_operators, load_device, open_dataset, open_store

__all__ = ["PSFDataset", "apply_noise", "NoiseRange"]


def apply_noise(psf: np.ndarray, rng: np.random.Generator, gaussian_percent: float = 0.0,
                photons_at_peak: float | None = None, read_noise_e: float = 0.0) -> np.ndarray:
    """Noise on an (8, S, S) normalised PSF tensor, each channel scaled by its own peak (the camera's
    exposure is set on the brightest spot): shot noise with ``photons_at_peak`` photo-electrons at the
    peak plus Gaussian read noise (electrons), then additive Gaussian noise of ``gaussian_percent`` % of
    the peak (the paper's noise levels, Fig. 3c-d).  The detector model is sensing's
    :func:`~metadesign.sensing.sensor.add_noise`; this names its levels as the datasets do (percent; read
    noise counts only with shot noise)."""
    return add_noise(psf, NoiseSpec(gaussian_sigma=gaussian_percent / 100.0, photons_at_peak=photons_at_peak or None,
                                    read_noise_e=read_noise_e if photons_at_peak else 0.0), rng)


def _span(name: str, v, lo: float, hi: float, open_lo: bool = False) -> tuple[float, float]:
    """A level or a ``(lo, hi)`` range of levels, checked; always a pair."""
    a, b = (v, v) if np.ndim(v) == 0 else tuple(v) if len(v) == 2 else (None, None)
    if a is None:
        raise ValidationError(f"{name}: expected a number or a range [lo, hi], got {v!r}")
    check_number(name, a, lo, hi, open_lo=open_lo)
    check_number(name, b, lo, hi, open_lo=open_lo)
    if a > b:
        raise ValidationError(f"{name}: expected a range [lo, hi] with lo <= hi, got {list(v)}")
    return float(a), float(b)


class NoiseRange:
    """The sensor noise of a split: Gaussian noise of ``gaussian_percent`` % of each channel's peak and
    optional shot (``photons_at_peak`` photo-electrons at the peak) + read noise.  Each level is a number or
    a range ``(lo, hi)``; a range is sampled per sample and epoch from the sample's own noise generator
    (uniform in percent, log-uniform in photons), so one model learns every level of the range and the
    draw is reproducible whatever the loader order (a fixed level draws nothing: the noise of a fixed-level
    run is unchanged)."""

    def __init__(self, gaussian_percent=0.0, photons_at_peak=None, read_noise_e: float = 0.0):
        self.gaussian = _span("gaussian_percent", gaussian_percent, 0, 100)
        self.photons = None if photons_at_peak is None or (np.ndim(photons_at_peak) == 0 and not photons_at_peak) \
            else _span("photons_at_peak", photons_at_peak, 0, 1e15, open_lo=True)
        check_number("read_noise_e", read_noise_e, 0, 1e6)
        self.read_noise_e = float(read_noise_e)

    @property
    def active(self) -> bool:
        return self.gaussian[1] > 0 or self.photons is not None

    def levels(self, rng: np.random.Generator) -> tuple[float, float | None]:
        """(Gaussian %, photons at peak) of one sample."""
        g0, g1 = self.gaussian
        g = g0 if g0 == g1 else float(rng.uniform(g0, g1))
        if self.photons is None:
            return g, None
        p0, p1 = self.photons
        return g, p0 if p0 == p1 else float(np.exp(rng.uniform(np.log(p0), np.log(p1))))

    def apply(self, psf: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        g, p = self.levels(rng)
        return apply_noise(psf, rng, g, p, self.read_noise_e)

    def describe(self) -> dict:
        """The levels as a model card records them: a number, or [lo, hi] for a range."""
        def one(r):
            return None if r is None else r[0] if r[0] == r[1] else list(r)
        return {"gaussian_percent": one(self.gaussian), "photons_at_peak": one(self.photons),
                "read_noise_e": self.read_noise_e}


class PSFDataset:
    """Samples of one split: ``{"psf": (8,S,S) float32, "received": (A,A) complex64, "rytov", "rytov_measured",
    "seed", "index", "loop_gain"}`` as torch tensors (``loop_gain``: 0 unless a ``[closed_loop]`` residual,
    then ``"mirror"`` (A,A) is the mirror's phase it was seen through: a correction's NPiB adds it), plus ``"screens"`` (regenerated) and ``"A"`` (the stored bucket
    operator) when asked.  Works with ``DataLoader(num_workers > 0)``: nothing but small
    metadata is read in the constructor; each worker opens the store on first use.  Noise levels are
    numbers or ``(lo, hi)`` ranges (:class:`NoiseRange`): ``noise`` holds its keywords
    (``gaussian_percent``, ``photons_at_peak``, ``read_noise_e``)."""

    def __init__(self, path: str | Path, split: str = "train", noise_seed: int = 0, limit: int | None = None,
                 screens: bool = False, operators: bool = False, **noise):
        if split not in ("train", "val", "test", "all"):
            raise ValidationError(f"split: expected train, val, test or all, got {split!r}")
        self.noise = NoiseRange(**noise)
        check_int("noise_seed", noise_seed, 0, 2**63 - 1)
        self.info = open_dataset(path)
        self.path = str(path)
        self.idx = self.info.indices(split)
        if limit is not None:
            self.idx = self.idx[:limit]
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

    @property
    def loop_residuals(self) -> int:
        """How many of this split's samples are closed-loop residuals (``[closed_loop]``; 0 for most stores)."""
        lg = self._arrays()["loop_gain"]
        return 0 if lg is None else int((lg[np.asarray(self.idx)] > 0).sum())

    def _arrays(self) -> dict:
        """The store's arrays by name, opened once per process (a group look-up costs ~0.5 ms: a tenth
        of a sample's load)."""
        if self._g is None:
            g = open_store(self.path)
            self._g = {k: g[k] for k in ("psf", "received", *(("pib_operator",) if "pib_operator" in g else ()))}
            # a [closed_loop] dataset: each sample's loop gain (0: an open-loop beacon), read once
            self._g["loop_gain"] = np.asarray(g["loop_gain"][:], np.float32) if "loop_gain" in g else None
            if "mirror_phase" in g:
                self._g["mirror_phase"] = g["mirror_phase"]
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
        if self.noise.active:
            rng = np.random.default_rng(np.random.SeedSequence(self.noise_seed, spawn_key=(self.epoch, i)))
            psf = self.noise.apply(psf, rng)
        out = {"psf": psf, "received": received, "rytov": float(self.info.rytov[i]),
               "rytov_measured": float(self.info.rytov_measured[i]), "seed": int(self.info.seed[i]), "index": i,
               "loop_gain": 0.0 if g["loop_gain"] is None else float(g["loop_gain"][i])}
        if "mirror_phase" in g:  # the mirror a closed-loop residual was seen through (zeros: open loop)
            out["mirror"] = np.asarray(g["mirror_phase"][i], np.float32)
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
                "loop_gain": torch.tensor(s["loop_gain"], dtype=torch.float32),
                **({"screens": torch.from_numpy(s["screens"])} if "screens" in s else {}),
                **({"mirror": torch.from_numpy(s["mirror"])} if "mirror" in s else {}),
                **({"A": torch.from_numpy(s["A"])} if "A" in s else {})}
