"""The device as the estimators see it: one typed object, built in one place.

A :class:`Device` is what every consumer of the forward model needs from a design as made: its coarse
pupil (the block-averaged, demodulated transmission of every pillar, :class:`~.forward.CoarsePupil`,
which carries the period, wavelength and focal distance), the sensor it images onto, and the
:class:`ReceiverCrop`: where the received field lives on the turbulence grid (the ``A x A`` crop of the
FFT-centred ``n_grid`` grid of pitch ``dx`` that holds the receiver aperture), which the pupil-field
interpolation, the differentiable twin, the retrieval, the Shack-Hartmann model and the import all share.

A dataset hands one out (:func:`metadesign.reconstruction.dataset.load_device`); the twin, retrieval,
Shack-Hartmann, capture import and the studies take it.  The wavelength is the pupil's; a turbulence
scenario at another wavelength is refused (:meth:`Device.check_wavelength`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..conventions import fft_centered
from ..io import read_npz, write_npz
from ..validation import ValidationError, check_int, check_number
from .forward import CoarsePupil
from .sensor import SensorSpec

__all__ = ["ReceiverCrop", "Device", "load_pupil", "save_pupil", "check_wavelengths", "WAVELENGTH_RTOL"]

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
class Device:
    """A metasurface as made, its sensor, and the received-field crop it is fed from."""

    pupil: CoarsePupil
    sensor: SensorSpec
    crop: ReceiverCrop

    def __post_init__(self):
        if not isinstance(self.pupil, CoarsePupil) or not isinstance(self.sensor, SensorSpec) \
                or not isinstance(self.crop, ReceiverCrop):
            raise TypeError("Device(pupil: CoarsePupil, sensor: SensorSpec, crop: ReceiverCrop)")

    @property
    def wavelength(self) -> float:
        return float(self.pupil.wavelength)

    @property
    def pupil_n(self) -> int:
        """Blocks per side of the coarse pupil."""
        return int(self.pupil.G.shape[-1])

    @property
    def geometry(self) -> tuple[int, int, int, float, float]:
        return self.crop.geometry

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
