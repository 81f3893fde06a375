"""Camera captures of the sensor: relay misalignment, exposure, camera noise, and synthetic captures.

**Alignment** (the convention shared with the importer, :mod:`metadesign.reconstruction.captures`):
a similarity transform of camera pixel coordinates ``p = (col, row)`` about the frame centre
``c = ((W - 1) / 2, (H - 1) / 2)``: light the nominal sensor model puts at pixel ``p`` lands at
``T(p) = s R(theta) (p - c) + c + t`` on the real camera (``t``: shift in pixels, ``theta``: rotation,
counter-clockwise in (col, row) coordinates, ``s``: relay magnification over its nominal value).

**Camera**: frames are exposed so that the brightest pixel of a sample's two frames reaches
``peak_counts`` (auto-exposure, ``overexpose`` > 1 drives it into saturation), with shot noise
(``photons_at_peak`` photo-electrons at ``peak_counts``), Gaussian read noise, a dark offset and hot
pixels (a fixed seeded set, present in dark frames too), quantised to unsigned ``bit_depth``-bit
integers (clipped at full scale, as a camera does).

**Synthetic captures** (:func:`metadesign.studies.captures.synth_captures`): the SLM shows the received *phase* of samples of an
existing dataset (a phase-only screen conjugate to the receiver aperture, as in the paper's lab,
Fig. 4); each frame is rendered through a device (its coarse pupil) onto an extended nominal frame and
sampled on the misaligned camera (cubic interpolation; the focal-plane image is ~20 pixels per
lambda / NA, so point sampling is pixel integration to < 1e-3); flat-wavefront and dark frames for the
calibration; a manifest ties them together.  The importer never sees the truth (``truth.json``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..conventions import centered
from ..determinism import single_thread_blas
from ..io import atomic_path
from ..optics.propagation import cexp
from ..validation import check_int, check_number
from .forward import quadrant_fields
from .sensor import photo_electrons
from .twin import crop_to_pupil

__all__ = ["Alignment", "CameraSpec", "extended_frames", "misaligned_frames", "expose", "slm_pupil_field",
           "write_frame"]


@dataclass(frozen=True)
class Alignment:
    shift_x_px: float = 0.0
    shift_y_px: float = 0.0
    rotation_deg: float = 0.0
    scale: float = 1.0

    def __post_init__(self):
        check_number("alignment.shift_x_px", self.shift_x_px, -200, 200)
        check_number("alignment.shift_y_px", self.shift_y_px, -200, 200)
        check_number("alignment.rotation_deg", self.rotation_deg, -10, 10)
        check_number("alignment.scale", self.scale, 0.8, 1.25)

    def _m(self):
        th = np.deg2rad(self.rotation_deg)
        return self.scale * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])

    @property
    def _t(self) -> np.ndarray:
        return np.array([self.shift_x_px, self.shift_y_px])

    @staticmethod
    def _centre(shape: tuple[int, int]) -> np.ndarray:
        return np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])

    @classmethod
    def from_matrix(cls, m: np.ndarray, t) -> "Alignment":
        """The alignment of a similarity matrix ``m`` (scale x rotation) and shift ``t`` (pixels)."""
        return cls(float(t[0]), float(t[1]), float(np.rad2deg(np.arctan2(m[1, 0], m[0, 0]))),
                   float(np.hypot(m[0, 0], m[1, 0])))

    def then(self, inner: "Alignment") -> "Alignment":
        """``self o inner``: apply ``inner`` in nominal coordinates, then ``self``."""
        m = self._m()
        return Alignment.from_matrix(m @ inner._m(), self._t + m @ inner._t)

    def forward(self, p: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Nominal pixel coordinates (..., 2) as (col, row) -> camera coordinates."""
        c = self._centre(shape)
        return (np.asarray(p, float) - c) @ self._m().T + c + self._t

    def inverse(self, q: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        c = self._centre(shape)
        return (np.asarray(q, float) - c - self._t) @ np.linalg.inv(self._m()).T + c

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class CameraSpec:
    peak_counts: float = 40000.0
    photons_at_peak: float = 20000.0
    read_noise_e: float = 5.0
    dark_counts: float = 100.0
    hot_pixels: int = 20
    hot_counts: float = 3000.0
    bit_depth: int = 16
    seed: int = 0

    def __post_init__(self):
        check_int("camera.bit_depth", self.bit_depth, 8, 16)
        full = 2**self.bit_depth - 1
        check_number("camera.peak_counts", self.peak_counts, 0, full, open_lo=True)
        check_number("camera.photons_at_peak", self.photons_at_peak, 0, 1e9)
        check_number("camera.read_noise_e", self.read_noise_e, 0, 1e4)
        check_number("camera.dark_counts", self.dark_counts, 0, full)
        check_int("camera.hot_pixels", self.hot_pixels, 0, 100000)
        check_number("camera.hot_counts", self.hot_counts, 0, full)
        check_int("camera.seed", self.seed, 0, 2**63 - 1)

    @property
    def full_scale(self) -> int:
        return 2**self.bit_depth - 1

    def hot_map(self, shape) -> np.ndarray:
        """(H, W) bool: the camera's hot pixels (seeded, fixed for the camera)."""
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(7,)))
        m = np.zeros(shape, bool)
        m.flat[rng.choice(m.size, self.hot_pixels, replace=False)] = True
        return m

    def to_dict(self) -> dict:
        return asdict(self)


def extended_frames(cp, sensor, e_in: np.ndarray | None, margin: int) -> np.ndarray:
    """(2, H + 2m, W + 2m) power per pixel of the nominal sensor model on a frame extended by ``margin``
    pixels on every side (each quadrant, extended outward, with its own non-paraxial centre)."""
    H, W, m = sensor.height_px, sensor.width_px, int(margin)
    p = sensor.focal_pitch
    X, Y = centered(W + 2 * m, p), centered(H + 2 * m, p)
    out = np.zeros((2, H + 2 * m, W + 2 * m), np.float32)
    h2, w2 = H // 2 + m, W // 2 + m
    with single_thread_blas():
        for pol in range(2):
            for k in range(1, 5):
                r = slice(0, h2) if k in (1, 2) else slice(h2, H + 2 * m)
                c = slice(0, w2) if k in (1, 3) else slice(w2, W + 2 * m)
                out[pol, r, c] = quadrant_fields(cp, pol, X[c], Y[r], sensor.quadrant_centre(k), e_in) * p * p
    return out


def misaligned_frames(cp, sensor, e_in: np.ndarray | None, alignment: Alignment, margin: int | None = None) -> np.ndarray:
    """(2, H, W) power per camera pixel on a misaligned camera: the nominal image at ``T^-1(q)``, divided
    by ``s^2`` (a pixel of the magnified image covers 1/s^2 of the focal area)."""
    from scipy.ndimage import map_coordinates

    H, W = sensor.height_px, sensor.width_px
    if margin is None:
        reach = np.hypot(W, H) / 2 * (abs(np.deg2rad(alignment.rotation_deg)) + abs(1 - 1 / alignment.scale))
        margin = int(np.ceil(reach + max(abs(alignment.shift_x_px), abs(alignment.shift_y_px)) + 4))
    ext = extended_frames(cp, sensor, e_in, margin)
    rr, cc = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    src = alignment.inverse(np.stack([cc, rr], -1).reshape(-1, 2), (H, W)) + margin
    out = np.empty((2, H, W), np.float32)
    for p in range(2):
        out[p] = map_coordinates(ext[p], [src[:, 1], src[:, 0]], order=3, mode="constant").reshape(H, W)
    return np.clip(out, 0, None) / np.float32(alignment.scale**2)


def expose(frames: np.ndarray, camera: CameraSpec, rng: np.random.Generator, hot: np.ndarray | None = None,
           overexpose: float = 1.0) -> np.ndarray:
    """Frames (..., H, W) of power -> unsigned integer counts (uint16): auto-exposure on the brightest
    pixel of all of them, shot and read noise, dark offset, hot pixels, quantisation and clipping.
    ``frames = 0`` gives dark frames."""
    f = np.asarray(frames, np.float64)
    peak = f.max()
    e = f / peak * camera.photons_at_peak * overexpose if peak > 0 else np.zeros_like(f)
    gain = camera.peak_counts / camera.photons_at_peak if camera.photons_at_peak else 0.0  # counts per e-
    if camera.photons_at_peak:  # the detector's one kernel (sensing.sensor.photo_electrons), on the electrons
        counts = photo_electrons(e, camera.read_noise_e, rng) * gain
    else:
        counts = (f / peak * camera.peak_counts * overexpose if peak > 0 else np.zeros_like(f))
    counts = counts + camera.dark_counts
    if hot is not None:
        counts = counts + np.where(hot, camera.hot_counts, 0.0)
    return np.clip(np.round(counts), 0, camera.full_scale).astype(np.uint16)


def slm_pupil_field(phase_crop: np.ndarray, geometry: tuple, n_out: int, pad: int = 4) -> np.ndarray:
    """The metasurface pupil field of a phase-only SLM screen ``phase_crop`` (A x A, on the receiver crop of
    the turbulence grid): the phase is extended by edge replication (the SLM is larger than the aperture),
    demagnified onto the metasurface as the turbulence stage does (cubic), cut to the pupil."""
    c0, a, ng, dx, d2 = geometry
    ph = np.pad(np.asarray(phase_crop, np.float64), pad, mode="edge")
    return crop_to_pupil(cexp(ph).astype(np.complex128), ng, dx, d2, c0 - pad, n_out)


def write_frame(path: Path, counts: np.ndarray) -> None:
    """A uint16 frame as 16-bit PNG or TIFF (Pillow), FITS (astropy: unsigned 16-bit as BZERO 32768) or
    .npy, by the suffix."""
    path = Path(path)
    with atomic_path(path) as tmp:
        if path.suffix == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, counts, allow_pickle=False)
        elif path.suffix == ".fits":
            from astropy.io import fits

            fits.PrimaryHDU(np.ascontiguousarray(counts, np.uint16)).writeto(tmp, overwrite=True)
        else:
            from PIL import Image

            Image.fromarray(np.ascontiguousarray(counts, np.uint16)).save(
                tmp, format="PNG" if path.suffix == ".png" else "TIFF")
