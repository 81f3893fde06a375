"""The device as the estimators see it: one typed object, built in one place.

A :class:`Device` is what every consumer of the forward model needs from a design as made: its coarse
pupil (the block-averaged, demodulated transmission of every pillar, :class:`~.forward.CoarsePupil`,
which carries the period, wavelength and focal distance), the sensor it images onto, and the
:class:`ReceiverCrop`: where the received field lives on the turbulence grid (the ``A x A`` crop of the
FFT-centred ``n_grid`` grid of pitch ``dx`` that holds the receiver aperture), which the pupil-field
interpolation, the differentiable twin, the retrieval, the Shack-Hartmann model and the import all share.

A dataset hands one out (:func:`metadesign.reconstruction.dataset.load_device`); the twin, retrieval,
Shack-Hartmann, capture import and the studies take it.  The wavelength is the pupil's; a turbulence
scenario at another wavelength is refused (:meth:`Device.check_wavelength`).

**The forward-model contract.**  A device renders its sensor's eight PSFs from an incident field, and every
backend of the model answers to the same three names (the loop in time calls them per frame):

===========================  ======================================================================
``pupil_field(crop)``        received crop(s) ``(..., A, A)`` -> incident field(s) on the coarse pupil grid
``psfs(e_in)``               incident pupil field(s) ``(..., N, N)`` -> PSF tensor(s) ``(..., 8, S, S)``
                             (power per tensor pixel, unit incident intensity, no noise)
``from_crop(crop)``          ``psfs(pupil_field(crop))``
===========================  ======================================================================

Backends: numpy, this class (exact: :func:`~.forward.sensor_frames` + :func:`~.sensor.psf_tensor`, one
field at a time; :meth:`Device.frames` and :meth:`Device.render` also give the camera frames); torch,
:meth:`Device.twin` (:class:`~.twin.TorchTwin`, batched and differentiable, the same operators); the
learnable diversity's :class:`~.twin_diversity.DiversityTwin`.  Noise is the detector's alone, after
rendering (:class:`~.detector.Detector`: :meth:`Device.render` with a detector in numpy,
``Detector.read_torch`` in torch); estimators receive frames, never noise settings.

**The camera.**  ``camera = None`` is today's ideal camera: the x-pol and y-pol frames rendered as two frames.  A
:class:`~.mosaic.MosaicCamera` (a polarisation camera: micro-polarisers on the pixels, issue #52) renders one raw
mosaic (:meth:`Device.raw`), which the detector reads (one exposure for both polarisations) and the camera
demosaics into the two frames on its own grid (:attr:`Device.frame_sensor`); the torch twins stay ideal."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..conventions import fft_centered
from ..io import read_npz, write_npz
from ..validation import ValidationError, check_int, check_number
from .detector import Detector
from .forward import CoarsePupil, sensor_frames
from .mosaic import MosaicCamera, render_raw
from .sensor import SensorSpec, psf_tensor
from .twin import TorchTwin, crop_to_pupil

__all__ = ["ReceiverCrop", "Device", "Exposure", "load_pupil", "save_pupil", "check_wavelengths", "WAVELENGTH_RTOL"]

#: relative tolerance of a wavelength match (float32 round-trips of nm values stay far below it)
WAVELENGTH_RTOL = 1e-6


@dataclass(frozen=True)
class ReceiverCrop:
    """The received field's ``size x size`` crop of the ``n_grid x n_grid`` turbulence grid (FFT-centred,
    pitch ``dx`` in m), starting at sample ``start`` on both axes, and the receiver aperture diameter
    (m) inside it."""

    start: int
    size: int
    n_grid: int
    dx: float
    aperture: float

    def __post_init__(self):
        check_int("received_crop.n_grid", self.n_grid, 2, 1 << 20)
        check_int("received_crop.size", self.size, 1, self.n_grid)
        check_int("received_crop.start", self.start, 0, self.n_grid - self.size)
        check_number("received_crop.dx", self.dx, 0, 1.0, open_lo=True, unit="m")
        check_number("received_crop.aperture", self.aperture, 0, 1e3, open_lo=True, unit="m")

    @classmethod
    def of_scenario(cls, scenario, start: int, size: int) -> "ReceiverCrop":
        return cls(int(start), int(size), int(scenario.n_grid), float(scenario.dx), float(scenario.receiver_aperture))

    @property
    def geometry(self) -> tuple[int, int, int, float, float]:
        """``(start, size, n_grid, dx, aperture)``: the argument order of the array kernels
        (:func:`metadesign.sensing.twin.crop_to_pupil`, :func:`~metadesign.sensing.twin.twin_operators`)."""
        return self.start, self.size, self.n_grid, self.dx, self.aperture

    @property
    def extent(self) -> float:
        """Side of the crop (m)."""
        return self.size * self.dx

    def coords(self) -> np.ndarray:
        """Sample coordinates of the crop along either axis (m; FFT-centred grid)."""
        return fft_centered(self.n_grid, self.dx)[self.start:self.start + self.size]

    def aperture_mask(self) -> np.ndarray:
        """(size, size) bool: the samples inside the receiver aperture."""
        x = self.coords()
        return (x[None, :] ** 2 + x[:, None] ** 2) <= (self.aperture / 2) ** 2

    def to_dict(self) -> dict:
        return {"start": self.start, "size": self.size, "n_grid": self.n_grid, "dx_m": self.dx,
                "aperture_m": self.aperture, "extent_m": self.extent}


@dataclass(frozen=True)
class Exposure:
    """One rendered exposure: the camera frames ``(2, H, W)`` (x- and y-polarisation; power per pixel for unit
    incident intensity, after the detector) and the PSF tensor ``(8, S, S)`` made from them; ``raw``: a mosaic
    camera's raw capture ``(2H, 2W)`` as the detector read it (None for the ideal camera)."""

    frames: np.ndarray
    psfs: np.ndarray
    raw: np.ndarray | None = None


@dataclass(frozen=True)
class Device:
    """A metasurface as made, its sensor, and the received-field crop it is fed from (None: a device fed
    with fields on its pupil grid only, e.g. the stage-4 PSF of a layout); ``camera``: a polarisation camera
    (:class:`~.mosaic.MosaicCamera`) in place of today's two ideal frames (None)."""

    pupil: CoarsePupil
    sensor: SensorSpec
    crop: ReceiverCrop | None = None
    camera: MosaicCamera | None = None

    def __post_init__(self):
        if not isinstance(self.pupil, CoarsePupil) or not isinstance(self.sensor, SensorSpec) \
                or not (self.crop is None or isinstance(self.crop, ReceiverCrop)) \
                or not (self.camera is None or isinstance(self.camera, MosaicCamera)):
            raise TypeError("Device(pupil: CoarsePupil, sensor: SensorSpec, crop: ReceiverCrop | None, "
                            "camera: MosaicCamera | None)")

    # -- the forward-model contract (numpy backend) -------------------------------------------------
    def frames(self, e_in: np.ndarray | None = None) -> np.ndarray:
        """Noise-free camera frames ``(2, H, W)`` for the incident field ``e_in`` on the pupil grid (None: a
        flat unit plane wave); a mosaic camera's demosaicked frames (on :attr:`frame_sensor`)."""
        if self.camera is None:
            return sensor_frames(self.pupil, self.sensor, e_in)
        return self.camera.demosaic(self.raw(e_in), self.sensor)

    def raw(self, e_in: np.ndarray | None = None) -> np.ndarray:
        """A mosaic camera's noise-free raw capture ``(2H, 2W)`` (power per pixel)."""
        if self.camera is None:
            raise ValidationError("this device has an ideal camera (two frames): no raw mosaic")
        return render_raw(self.pupil, self.sensor, self.camera, e_in)

    @property
    def frame_sensor(self) -> SensorSpec:
        """The grid of the frames: the sensor's, or a mosaic camera's super-pixels over its field."""
        return self.sensor if self.camera is None else self.camera.frame_sensor(self.sensor)

    def _read(self, frames: np.ndarray, detector: Detector | None, rng) -> Exposure:
        """What the camera records of noise-free ``frames`` (a mosaic camera's: its raw capture)."""
        if detector is not None:
            frames = detector.read(frames, rng)
        if self.camera is None:
            return Exposure(frames, psf_tensor(frames, self.sensor))
        f = self.camera.demosaic(frames, self.sensor)
        return Exposure(f, psf_tensor(f, self.frame_sensor), frames)

    def render(self, e_in: np.ndarray | None = None, detector: Detector | None = None,
               rng: np.random.Generator | None = None) -> Exposure:
        """The one call per frame: the frames of ``e_in``, read by the ``detector`` (None: noise-free; ``rng``
        its draws, else its seed's), and the PSF tensor of what it read (a mosaic camera: its raw capture is
        read, then demosaicked)."""
        return self._read(self.frames(e_in) if self.camera is None else self.raw(e_in), detector, rng)

    def expose(self, fields, detector: Detector | None = None, rng: np.random.Generator | None = None) -> Exposure:
        """One exposure over moving turbulence: the mean of the noise-free frames of each incident field of
        ``fields`` (the exposure's sub-steps), read once by the ``detector`` (its photon budget is the
        frame's), and the PSF tensor of what it read.  One field: :meth:`render`."""
        one = self.frames if self.camera is None else self.raw
        frames = np.mean([one(e) for e in fields], axis=0, dtype=np.float64).astype(np.float32)
        return self._read(frames, detector, rng)

    def psfs(self, e_in: np.ndarray | None = None) -> np.ndarray:
        """The noise-free PSF tensor ``(8, S, S)`` (or ``(B, 8, S, S)`` for a batch of fields)."""
        if e_in is not None and np.ndim(e_in) == 3:
            return np.stack([self.psfs(e) for e in e_in])
        return psf_tensor(self.frames(e_in), self.frame_sensor)

    def pupil_field(self, crop: np.ndarray) -> np.ndarray:
        """Received crop(s) ``(..., A, A)`` -> the incident field(s) on the pupil grid (the cubic resampling
        of :meth:`~metadesign.turbulence.propagate.Turbulence.to_metasurface`, the metasurface's mask)."""
        c = self._need_crop()
        crop = np.asarray(crop)
        if crop.ndim == 3:
            return np.stack([self.pupil_field(x) for x in crop])
        return crop_to_pupil(crop, c.n_grid, c.dx, c.aperture, c.start, self.pupil_n)

    def from_crop(self, crop: np.ndarray) -> np.ndarray:
        return self.psfs(self.pupil_field(crop))

    def twin(self, rebin: int = 1, samples: int | None = None, device="cpu", double: bool = False):
        """The torch backend of this device (:class:`~metadesign.sensing.twin.TorchTwin`: the same three
        calls, batched, differentiable; an ideal camera's)."""
        if self.camera is not None:
            raise ValidationError("the torch twin renders an ideal camera's two frames: a device with a mosaic "
                                  "camera has no twin (use Device(pupil, sensor, crop) for it)")
        return TorchTwin.for_device(self, rebin, samples, device, double)

    def _need_crop(self) -> ReceiverCrop:
        if self.crop is None:
            raise ValidationError("this device has no receiver crop: it takes fields on its pupil grid only")
        return self.crop

    @property
    def wavelength(self) -> float:
        return float(self.pupil.wavelength)

    @property
    def pupil_n(self) -> int:
        """Blocks per side of the coarse pupil."""
        return int(self.pupil.G.shape[-1])

    @property
    def geometry(self) -> tuple[int, int, int, float, float]:
        return self._need_crop().geometry

    def check_wavelength(self, wavelength: float, what: str = "turbulence scenario") -> None:
        """Refuse a field at another wavelength than the device's (one line naming both)."""
        check_wavelengths(self.wavelength, wavelength, what)


def check_wavelengths(device_wavelength: float, wavelength: float, what: str = "turbulence scenario") -> None:
    if not np.isclose(float(wavelength), float(device_wavelength), rtol=WAVELENGTH_RTOL, atol=0.0):
        raise ValidationError(f"{what}: wavelength {float(wavelength) * 1e9:.6g} nm does not match the device's "
                              f"{float(device_wavelength) * 1e9:.6g} nm")


def save_pupil(path: str | Path, cp: CoarsePupil, **extra) -> None:
    """Write a coarse pupil (atomically) as ``.npz``, with ``extra`` arrays (e.g. a cache key)."""
    write_npz(Path(path), {"G": cp.G, "X": cp.X, "block": cp.block, "period": cp.period,
                           "wavelength": cp.wavelength, "z": cp.z, "n_clamped": cp.n_clamped, **extra})


def load_pupil(path: str | Path, z: dict | None = None) -> CoarsePupil:
    """A coarse pupil stored by :func:`save_pupil` (``device-pupil.npz`` of a dataset); ``z``: its arrays,
    when already read."""
    z = read_npz(Path(path), "device pupil") if z is None else z
    need = ("G", "X", "block", "period", "wavelength", "z", "n_clamped")
    missing = [k for k in need if k not in z]
    if missing:
        raise ValidationError(f"{path}: device pupil lacks {', '.join(missing)}")
    G = np.asarray(z["G"])
    if G.ndim != 4 or G.shape[0] != 2 or not np.isfinite(G).all():
        raise ValidationError(f"{path}: device pupil: expected finite G of shape (2, m*m, N, N), got {G.shape}")
    return CoarsePupil(G, z["X"], int(z["block"]), float(z["period"]), float(z["wavelength"]), float(z["z"]),
                       int(z["n_clamped"]))
