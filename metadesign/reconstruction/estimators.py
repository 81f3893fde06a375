"""Wavefront estimators: one interface, one registry (hcipy's ``WavefrontSensorEstimator`` in spirit).

An estimator turns what its sensor sees into a phase estimate on the received-field crop ``(B, A, A)``
(rad; the correction applied is its conjugate).  Construction is the latency-irrelevant ``prepare`` step
(operators, contexts, calibration); :meth:`Estimator.estimate` is the batch path; :meth:`Estimator.
latency_fn` is the single-sample call a latency figure times.  Iterative estimators also report their
estimate at checkpoints along the iterations (``on_checkpoint(iteration, phi)``), so a study can draw
NPiB against latency.

A new estimator is one class with :func:`register`::

    @register
    class MyEstimator(Estimator):
        name, label = "mine", "my method"
        def estimate(self, batch, done=None, on_checkpoint=None): ...

Studies (``metadesign compare``) build every registered estimator from a :class:`~metadesign.sensing.
device.Device` and the estimator's own settings (``config_key``: the attribute of the study's settings
that holds them) and run them on the same samples and the same sensor noise.

A batch is a dict of numpy arrays of one dataset split: ``psf`` (B, 8, S, S) as the detector read them,
``received`` (B, A, A) complex (the true field: what a Shack-Hartmann sensor in the same plane would see),
``index`` (B,) sample indices, and ``sh_spots`` (B, L, L, K, K): a Shack-Hartmann sensor's spot images as
its detector read them (:func:`sh_exposures`; noise-free spots of ``received`` when absent).  Estimators
never see noise settings: the detector (:mod:`metadesign.sensing.detector`) made their input; what an
estimator assumes of its data (the retrieval's likelihood, a centroid threshold) is its own config."""

from __future__ import annotations

from typing import Callable, ClassVar

import numpy as np

from ..sensing.device import Device
from ..validation import ValidationError
from .retrieval import RetrievalConfig, RetrievalContext, retrieve
from .shack_hartmann import ShackHartmann, SHConfig

__all__ = ["Estimator", "register", "ESTIMATORS", "estimator_names", "make_estimator", "checkpoints_for", "sh_exposures",
           "UNetEstimator", "RetrievalEstimator", "HybridEstimator", "ShackHartmannEstimator", "RefineEstimator"]

#: name -> estimator class, in registration order (the order studies run and list them)
ESTIMATORS: dict[str, type["Estimator"]] = {}


def register(cls: type["Estimator"]) -> type["Estimator"]:
    """Class decorator: add an estimator to the registry under ``cls.name``."""
    if not cls.name or cls.name in ESTIMATORS:
        raise ValueError(f"estimator name {cls.name!r} is empty or taken")
    ESTIMATORS[cls.name] = cls
    return cls


def estimator_names() -> tuple[str, ...]:
    return tuple(ESTIMATORS)


def checkpoints_for(total: int) -> list[int]:
    """0, 1, 2, 5, 10, 20, 50, ... up to ``total`` (and ``total``)."""
    out, base = [0], 1
    while base <= total:
        out += [c for c in (base, 2 * base, 5 * base) if c <= total]
        base *= 10
    return sorted(set(out + [total]))


class Estimator:
    """The interface; subclasses set the class attributes and implement :meth:`estimate`."""

    name: ClassVar[str] = ""
    label: ClassVar[str] = ""
    style: ClassVar[tuple[str, str]] = ("k", "o")  # matplotlib colour and marker in study figures
    needs_model: ClassVar[bool] = False  # takes the U-Net (the model argument of a study)
    needs_refiner: ClassVar[bool] = False  # takes a trained refiner (a study's model argument when it is one)
    config_key: ClassVar[str | None] = None  # attribute of a study's settings holding this estimator's config
    starts_from: ClassVar[str | None] = None  # the estimator whose estimate it starts from (its latency adds)
    own_sensor: ClassVar[bool] = False  # reads its own sensor's frames, not the metasurface's PSFs

    def __init__(self, device: Device, config=None, model=None):
        """The ``prepare`` step: everything that does not depend on the sample (not timed)."""
        self.device, self.config, self.model = device, config, model
        if self.needs_model and model is None:
            raise ValidationError(f"estimator {self.name}: needs a model")

    @property
    def iterations(self) -> int | None:
        """Iterations of an iterative estimator (None: one shot)."""
        return None

    def checkpoints(self) -> list[int]:
        return checkpoints_for(self.iterations) if self.iterations is not None else []

    def estimate(self, batch: dict, done: dict | None = None,
                 on_checkpoint: Callable[[int, object], None] | None = None):
        """Phase estimates (B, A, A) for a batch (a torch tensor or a numpy array).  ``done``: estimates of
        the estimators run before on the same batch, by name (the hybrid starts from the U-Net's)."""
        raise NotImplementedError

    def latency_fn(self, item: dict, done: dict | None = None) -> Callable[[], object]:
        """A zero-argument call estimating one sample (``item``: a batch of one), for timing."""
        return lambda: self.estimate(item, done)

    def misfit(self):
        """Per-iteration data misfit of the last :meth:`estimate` (iterative estimators), or None."""
        return None


def _torch(a):
    import torch

    return a if isinstance(a, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(a))


@register
class ShackHartmannEstimator(Estimator):
    """A simulated Shack-Hartmann sensor in the received-field plane: centroids and reconstruction of its
    spot images (``batch["sh_spots"]``, as its detector read them: :func:`sh_exposures`), the centroid
    threshold set by its config's ``noise_percent``."""

    name, label, style, config_key = "shack_hartmann", "Shack-Hartmann", ("tab:orange", "v"), "sh"
    own_sensor = True  # its input is not the metasurface's PSFs: a study renders its spots (sh_exposures)

    def __init__(self, device: Device, config: SHConfig | None = None, model=None):
        super().__init__(device, config or SHConfig(), model)
        self.sh = ShackHartmann.for_device(self.config, device)

    def _spots(self, batch) -> np.ndarray:
        if "sh_spots" in batch:
            return np.asarray(batch["sh_spots"])
        return self.sh.frames(np.asarray(batch["received"]))  # a noise-free detector

    def estimate(self, batch, done=None, on_checkpoint=None):
        out = [self.sh.reconstruct(*self.sh.centroids(s[None], self.config.noise_percent))[0]
               for s in self._spots(batch)]
        return _torch(np.stack(out))

    def latency_fn(self, item, done=None):
        spots = self._spots(item)[:1]  # the sensor's exposure is not the estimator's latency
        return lambda: self.sh.reconstruct(*self.sh.centroids(spots, self.config.noise_percent))


def sh_exposures(est: ShackHartmannEstimator, received: np.ndarray, index: np.ndarray, noise_percent: float,
                 noise_seed: int) -> np.ndarray:
    """The spot images (B, L, L, K, K) of the Shack-Hartmann sensor of ``est`` for received crops (B, A, A),
    read by its detector: Gaussian noise of ``noise_percent`` % of each frame's peak, seeded per sample
    (``SeedSequence(noise_seed, spawn_key=(7, index))``).  The study's side of the sensor, not the
    estimator's."""
    out = []
    for r, i in zip(received, index):
        rng = np.random.default_rng(np.random.SeedSequence(int(noise_seed), spawn_key=(7, int(i))))
        out.append(est.sh.add_noise(est.sh.frames(np.asarray(r)[None]), noise_percent, rng)[0])
    return np.stack(out)


@register
class RetrievalEstimator(Estimator):
    """Model-based phase-diversity retrieval through the differentiable twin (Zernike coarse-to-fine from
    several starts, then per-pixel phase and amplitude)."""

    name, label, style, config_key = "retrieval", "PD retrieval", ("tab:purple", "D"), "retrieval"

    def __init__(self, device: Device, config: RetrievalConfig | None = None, model=None):
        super().__init__(device, config or RetrievalConfig(misfit="gaussian"), model)
        self.ctx = RetrievalContext.build(device, self.config)
        self._misfit = None

    @property
    def iterations(self) -> int:
        return self.config.iterations

    def start(self, batch, done):
        return None

    def estimate(self, batch, done=None, on_checkpoint=None):
        out = retrieve(_torch(batch["psf"]), self.ctx, self.config, init=self.start(batch, done),
                       checkpoints=self.checkpoints() if on_checkpoint else (), on_checkpoint=on_checkpoint)
        self._misfit = out["misfit"]
        return out["phi"]

    def misfit(self):
        return self._misfit


@register
class UNetEstimator(Estimator):
    """The U-Net: one forward pass on the 8 PSFs."""

    name, label, style, needs_model = "unet", "U-Net", ("tab:blue", "o"), True

    def estimate(self, batch, done=None, on_checkpoint=None):
        import torch

        with torch.no_grad():
            return self.model(_torch(batch["psf"]))


@register
class HybridEstimator(RetrievalEstimator):
    """The retrieval started from the U-Net's estimate (fewer, finer iterations)."""

    name, label, style, config_key, needs_model = "hybrid", "U-Net + retrieval", ("tab:red", "*"), "hybrid", True
    starts_from = "unet"
    DEFAULT = RetrievalConfig(modal_iterations=0, zonal_iterations=50, lr_zonal=0.03, misfit="gaussian")

    def __init__(self, device: Device, config: RetrievalConfig | None = None, model=None):
        super().__init__(device, config or self.DEFAULT, model)

    def start(self, batch, done):
        import torch

        if done and self.starts_from in done:
            return done[self.starts_from]
        with torch.no_grad():
            return self.model(_torch(batch["psf"]))


@register
class RefineEstimator(Estimator):
    """The learned refinement (:mod:`.refine`): the U-Net's estimate, then K unrolled steps through the
    twin; its estimate after each step is a checkpoint (NPiB against K and against latency)."""

    name, label, style = "refine", "U-Net + learned refinement", ("tab:cyan", "P")
    needs_model, needs_refiner, starts_from = True, True, "unet"

    @property
    def iterations(self) -> int:
        return len(self.model.steps)

    def estimate(self, batch, done=None, on_checkpoint=None):
        import torch

        start = done.get(self.starts_from) if done else None
        with torch.no_grad():  # each step's estimate reported as it is computed (latency per K)
            for k, phi in enumerate(self.model.iterate(_torch(batch["psf"]),
                                                       start=None if start is None else _torch(start))):
                if on_checkpoint is not None:
                    on_checkpoint(k, phi * self.model.mask)
        return phi * self.model.mask


def make_estimator(name: str, device: Device, settings=None, model=None, refiner=None) -> Estimator:
    """The registered estimator ``name`` for ``device``; its config is ``getattr(settings, config_key)``;
    ``model`` the U-Net, ``refiner`` a trained refiner (for the estimators that need one)."""
    if name not in ESTIMATORS:
        raise ValidationError(f"estimator: expected one of {', '.join(ESTIMATORS)}, got {name!r}")
    cls = ESTIMATORS[name]
    cfg = getattr(settings, cls.config_key) if settings is not None and cls.config_key else None
    if cls.needs_refiner and refiner is None:
        raise ValidationError(f"estimator {name}: needs a trained refiner (give its .safetensors as the model)")
    return cls(device, cfg, refiner if cls.needs_refiner else model)
