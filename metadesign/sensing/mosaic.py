"""A division-of-focal-plane polarisation camera: a 2 x 2 mosaic of micro-polarisers on the pixels (issue #52).

The paper's single shot needs one camera that records both polarisation frames at once: "a wire grid polarizer on
each pixel" (Sony's IMX250MZR and its kin: a 2 x 2 super-pixel of 0/45/90/135 degree micro-polarisers).  Today's
forward model renders the x-pol and y-pol frames as two ideal frames; :class:`MosaicCamera` is the camera element
that turns the field at the sensor into one raw mosaic capture, and the raw capture back into the two frames.

**Physics** (pure array kernels, SI):

* The field at the sensor has an x and a y component, the metasurface's two polarisation channels.  They are
  rendered as complex amplitudes (:func:`~.forward.quadrant_transform`), each for unit incident intensity in its
  own polarisation (today's frames are their squares), so the incident beam's state enters as the relative phase
  ``delta`` of its y component: ``E = (a_x, a_y exp(i delta))``.  ``circular`` (``delta = 90 deg``, the paper's lab:
  a quarter-wave plate before the metasurface), ``linear-45`` (``delta = 0``), or ``unpolarised`` (the two
  components mutually incoherent: the cross term vanishes, the incoherent case).  The common factor 1/2 of a
  real beam split over two channels is left out: the frames are normalised by their peak downstream.
* A micro-polariser at angle ``theta`` is a partial polariser: Jones matrix ``R(theta) diag(sqrt(T),
  sqrt(T / ER)) R(-theta)`` (principal intensity transmittances ``T`` along ``theta`` and ``T / ER`` across it).
  With ``u = (cos theta, sin theta)`` and ``|u . E|^2 + |u_perp . E|^2 = |E|^2``::

      I_theta = T [ (1 - 1/ER) |E_x cos theta + E_y sin theta|^2 + |E|^2 / ER ]
              = T [ (1 - 1/ER) (c^2 I_x + s^2 I_y + 2 c s Re(E_x E_y*)) + (I_x + I_y) / ER ]

  (:func:`polariser_intensity`): Malus's law ``T cos^2 theta`` for x-polarised light at ``ER = inf``, and ``T / ER``
  for light polarised across the pass axis.  The 0 and 90 degree pixels see no cross term (``I_0 = T (I_x + I_y /
  ER)``); the diagonal pixels do, so coherence matters only when they are used.
* Pixel crosstalk: a fraction ``c`` of each pixel's power leaks to its four neighbours (``c / 4`` each; light
  leaking off the array is lost): a 5-point convolution on the raw mosaic (:func:`pixel_crosstalk`).  Its
  neighbours of a 0 degree pixel are diagonal ones, so ``c`` acts like an extinction leak ``~ c / 2``.
* The 2 x 2 super-pixel ``pattern`` (rows of angles in degrees, top row first; the IMX250MZR's is ``[[90, 45],
  [135, 0]]``) and the demosaic at half resolution (:func:`demosaic`): the x frame from the 0 degree pixels and the
  y frame from the 90 degree ones, or, with ``use_diagonal``, from the Stokes parameters of all four
  (``S0 = (I0 + I45 + I90 + I135) / 2``, ``S1 = I0 - I90``; ``x = (S0 + S1) / 2``, ``y = (S0 - S1) / 2``, which
  averages two measurements of the total); ``unmix`` removes a known extinction leak (:func:`unmix`).
* Resolution: the mosaic's pixel pitch ``pixel_pitch`` (on the camera, behind the same relay as the sensor's) gives
  half-resolution frames of pitch ``2 pixel_pitch``.  The camera covers the sensor's field; its frames are the
  sensor's grid when ``pixel_pitch`` is half the sensor's (the default), 2x coarser when it equals it.  With
  ``offsets`` each micro-polariser samples the field at its own pixel's centre (the x and y frames are then one
  pixel apart diagonally, as on the chip); without, every pixel of a super-pixel samples its centre (the
  super-pixel idealisation).  Ideal polarisers (``ER = inf``, ``T = 1``), no crosstalk, no offsets and the default
  pitch give today's frames exactly (test).

The element composes with the one detector (:class:`~.detector.Detector`): :class:`~.device.Device` renders the raw
mosaic, the detector reads it (one exposure, one peak for both polarisations), then the camera demosaics."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..determinism import single_thread_blas
from ..validation import ConfigError, check_number
from .forward import quadrant_transform
from .sensor import SensorSpec, quadrant_slices

__all__ = [
    "ANGLES",
    "IMX250MZR_PATTERN",
    "INCIDENT",
    "MosaicCamera",
    "camera_frames",
    "check_pattern",
    "demosaic",
    "fields_key",
    "interleave",
    "pixel_crosstalk",
    "polariser_intensity",
    "raw_of_sites",
    "render_raw",
    "site_fields",
    "sites",
    "stokes",
    "unmix",
]

#: the micro-polariser angles of a division-of-focal-plane camera (degrees)
ANGLES = (0, 45, 90, 135)
#: Sony's IMX250MZR / IMX253MZR super-pixel (rows top to bottom, degrees)
IMX250MZR_PATTERN = ((90, 45), (135, 0))
#: the incident beam's polarisation states: the y component's phase relative to x (deg), None: incoherent
INCIDENT = {"circular": 90.0, "linear-45": 0.0, "unpolarised": None}


def _trig(theta_deg: float) -> tuple[float, float, float]:
    """``(cos^2, sin^2, cos sin)`` of ``theta``, exact at multiples of 45 degrees (no 6e-17 leftovers)."""
    c2 = math.cos(math.radians(2 * theta_deg))
    s2 = math.sin(math.radians(2 * theta_deg))
    c2, s2 = (0.0 if abs(v) < 1e-12 else v for v in (c2, s2))
    return (1 + c2) / 2, (1 - c2) / 2, s2 / 2


def polariser_intensity(ix, iy, cross, theta_deg: float, transmission: float = 1.0,
                        extinction_ratio: float = math.inf):
    """Intensity behind a partial polariser at ``theta_deg`` (principal transmittances ``transmission`` and
    ``transmission / extinction_ratio``) of a field with ``|E_x|^2 = ix``, ``|E_y|^2 = iy`` and ``Re(E_x E_y*) =
    cross`` (0 for mutually incoherent components); arrays of one shape, or scalars."""
    c2, s2, cs = _trig(theta_deg)
    leak = 0.0 if math.isinf(extinction_ratio) else 1.0 / extinction_ratio
    proj = c2 * ix + s2 * iy
    if cs:
        proj = proj + (2 * cs) * cross
    out = (1.0 - leak) * proj
    if leak:
        out = out + leak * (ix + iy)
    return out if transmission == 1.0 else transmission * out


def check_pattern(pattern, where: str = "camera.pattern") -> tuple[tuple[int, int], tuple[int, int]]:
    """A 2 x 2 super-pixel: rows of angles, each of 0, 45, 90, 135 degrees once."""
    try:
        rows = tuple(tuple(float(v) for v in row) for row in pattern)
    except (TypeError, ValueError):
        raise ConfigError(where, f"expected 2 rows of 2 angles (degrees), got {pattern!r}") from None
    flat = [v for row in rows for v in row]
    if len(rows) != 2 or any(len(r) != 2 for r in rows) or sorted(flat) != [0.0, 45.0, 90.0, 135.0]:
        raise ConfigError(where, f"expected 2 rows of 2 angles holding 0, 45, 90 and 135 degrees once each "
                                 f"(the IMX250MZR's: [[90, 45], [135, 0]]), got {pattern!r}")
    return tuple(tuple(int(v) for v in row) for row in rows)


def sites(pattern) -> dict[int, tuple[int, int]]:
    """Angle -> (row, column) of its pixel in the super-pixel."""
    return {int(pattern[r][c]): (r, c) for r in range(2) for c in range(2)}


def interleave(site_images: dict, pattern) -> np.ndarray:
    """The raw mosaic ``(2H, 2W)`` of four ``(H, W)`` images, one per angle, at their pattern sites."""
    first = next(iter(site_images.values()))
    h, w = first.shape[-2:]
    raw = np.empty(first.shape[:-2] + (2 * h, 2 * w), first.dtype)
    for ang, (r, c) in sites(pattern).items():
        raw[..., r::2, c::2] = site_images[ang]
    return raw


def pixel_crosstalk(raw: np.ndarray, fraction: float) -> np.ndarray:
    """Each pixel keeps ``1 - fraction`` of its power and gives ``fraction / 4`` to each of its four neighbours
    (what leaks off the array is lost): the power inside the array is conserved."""
    if not fraction:
        return raw
    raw = np.asarray(raw)
    f = raw.astype(np.float64)
    out = (1.0 - fraction) * f
    q = fraction / 4.0
    out[..., 1:, :] += q * f[..., :-1, :]
    out[..., :-1, :] += q * f[..., 1:, :]
    out[..., :, 1:] += q * f[..., :, :-1]
    out[..., :, :-1] += q * f[..., :, 1:]
    return out.astype(raw.dtype)


def stokes(i0, i45, i90, i135) -> tuple:
    """The linear Stokes parameters of a super-pixel: ``S0 = (I0 + I45 + I90 + I135) / 2``, ``S1 = I0 - I90``,
    ``S2 = I45 - I135``."""
    return (i0 + i45 + i90 + i135) / 2, i0 - i90, i45 - i135


def unmix(x, y, transmission: float = 1.0, extinction_ratio: float = math.inf):
    """The x and y intensities from the 0 and 90 degree measurements ``x = T (I_x + I_y / ER)``, ``y = T (I_y +
    I_x / ER)`` of a camera of known ``T`` and ``ER`` (the inverse of the 2 x 2 leak)."""
    if math.isinf(extinction_ratio):
        return (x, y) if transmission == 1.0 else (x / transmission, y / transmission)
    e = 1.0 / extinction_ratio
    d = transmission * (1.0 - e * e)
    return (x - e * y) / d, (y - e * x) / d


def demosaic(raw: np.ndarray, pattern, use_diagonal: bool = False) -> np.ndarray:
    """``(2, H, W)`` x and y frames at half resolution from a raw mosaic ``(..., 2H, 2W)`` (in the raw pixels'
    units): the 0 and 90 degree pixels, or the Stokes estimate of all four (``use_diagonal``)."""
    raw = np.asarray(raw)
    s = sites(pattern)
    px = {a: raw[..., r::2, c::2] for a, (r, c) in s.items()}
    if not use_diagonal:
        return np.stack([px[0], px[90]], axis=-3)
    s0, s1, _ = stokes(*(px[a].astype(np.float64) for a in ANGLES))
    return np.stack([(s0 + s1) / 2, (s0 - s1) / 2], axis=-3).astype(raw.dtype)


@dataclass(frozen=True)
class MosaicCamera:
    """A division-of-focal-plane polarisation camera (the module's docstring has the physics).

    ``extinction_ratio``: ``inf`` for ideal polarisers (a recipe writes 0); ``transmission``: the pass axis's
    intensity transmittance; ``crosstalk``: the fraction of a pixel's power leaking to its 4 neighbours;
    ``pixel_pitch``: the mosaic's pixel pitch on the camera (m; None: half the sensor's, so the frames keep its
    grid); ``use_diagonal``: demosaic through the Stokes parameters of all four pixels; ``unmix``: correct the
    known extinction leak; ``offsets``: each pixel samples its own centre; ``incident``: the incident beam's
    polarisation (:data:`INCIDENT`)."""

    pattern: tuple = IMX250MZR_PATTERN
    extinction_ratio: float = math.inf
    transmission: float = 1.0
    crosstalk: float = 0.0
    pixel_pitch: float | None = None
    use_diagonal: bool = False
    unmix: bool = False
    offsets: bool = True
    incident: str = "circular"

    def __post_init__(self):
        object.__setattr__(self, "pattern", check_pattern(self.pattern))
        er = self.extinction_ratio
        if not (isinstance(er, (int, float)) and not isinstance(er, bool) and (math.isinf(er) and er > 0 or
                                                                                math.isfinite(er) and er > 1)):
            raise ConfigError("camera.extinction_ratio", f"expected a number > 1 (0 in a recipe: ideal polarisers), "
                                                         f"got {er!r}")
        check_number("camera.transmission", self.transmission, 0, 1, open_lo=True)
        check_number("camera.crosstalk", self.crosstalk, 0, 0.5, open_hi=True)
        if self.pixel_pitch is not None:
            check_number("camera.pixel_pitch", self.pixel_pitch, 0, 1e-3, open_lo=True, unit="m")
        if self.incident not in INCIDENT:
            raise ConfigError("camera.incident", f"expected one of {', '.join(map(repr, INCIDENT))}, got "
                                                 f"{self.incident!r}")

    @property
    def ideal(self) -> bool:
        """Ideal polarisers, no crosstalk: the frames of an ideal camera (on the camera's grid)."""
        return math.isinf(self.extinction_ratio) and self.transmission == 1.0 and not self.crosstalk

    def pitch(self, sensor: SensorSpec) -> float:
        """The mosaic's pixel pitch on the camera (m)."""
        return sensor.pixel_pitch / 2 if self.pixel_pitch is None else self.pixel_pitch

    def frame_sensor(self, sensor: SensorSpec) -> SensorSpec:
        """The sensor of the demosaicked frames: the camera's super-pixels over the sensor's field."""
        p = self.pitch(sensor)
        if p == sensor.pixel_pitch / 2:
            return sensor
        dims = []
        for name, n in (("width_px", sensor.width_px), ("height_px", sensor.height_px)):
            m = n * sensor.pixel_pitch / (2 * p)
            if abs(m - round(m)) > 1e-6 * m or round(m) % 4 or round(m) < 4:
                raise ConfigError("camera.pixel_pitch_um", f"{p * 1e6:g} um: the sensor's field ({name} x pixel_um "
                                  f"= {n * sensor.pixel_pitch * 1e6:g} um) must span a multiple of 8 mosaic pixels "
                                  f"(e.g. pixel_pitch_um = {sensor.pixel_pitch * 1e6 / 2:g} or "
                                  f"{sensor.pixel_pitch * 1e6:g})")
            dims.append(round(m))
        return SensorSpec(dims[0], dims[1], 2 * p, sensor.magnification, sensor.distance, sensor.tensor_size)

    def raw_shape(self, sensor: SensorSpec) -> tuple[int, int]:
        fs = self.frame_sensor(sensor)
        return 2 * fs.height_px, 2 * fs.width_px

    def offsets_of(self, sensor: SensorSpec) -> dict[int, tuple[float, float]]:
        """Angle -> (x, y) of its pixel's centre from its super-pixel's, in the focal plane (m)."""
        if not self.offsets:
            return {a: (0.0, 0.0) for a in ANGLES}
        q = self.pitch(sensor) / sensor.magnification / 2
        return {a: ((2 * c - 1) * q, (2 * r - 1) * q) for a, (r, c) in sites(self.pattern).items()}

    def area_ratio(self, sensor: SensorSpec) -> float:
        """A super-pixel's area over one pixel's: the demosaicked frames are power per super-pixel."""
        return (self.frame_sensor(sensor).focal_pitch / (self.pitch(sensor) / sensor.magnification)) ** 2

    def demosaic(self, raw: np.ndarray, sensor: SensorSpec) -> np.ndarray:
        """``(2, H, W)`` frames (power per super-pixel, the leak corrected with ``unmix``) from a raw mosaic."""
        f = demosaic(raw, self.pattern, self.use_diagonal) * np.float32(self.area_ratio(sensor))
        if self.unmix:
            x, y = unmix(f[..., 0, :, :].astype(np.float64), f[..., 1, :, :].astype(np.float64), self.transmission,
                         self.extinction_ratio)
            f = np.stack([x, y], axis=-3).astype(f.dtype)
        return f

    def to_dict(self) -> dict:
        return {"kind": "mosaic", "pattern": [list(r) for r in self.pattern],
                "extinction_ratio": None if math.isinf(self.extinction_ratio) else self.extinction_ratio,
                "transmission": self.transmission, "crosstalk_percent": self.crosstalk * 100,
                "pixel_pitch_um": None if self.pixel_pitch is None else round(self.pixel_pitch * 1e6, 6),
                "use_diagonal": self.use_diagonal, "unmix": self.unmix, "offsets": self.offsets,
                "incident": self.incident}


def fields_key(camera: MosaicCamera, sensor: SensorSpec) -> tuple:
    """What :func:`site_fields` depends on of a camera: cameras with one key share their fields."""
    return camera.pitch(sensor), camera.offsets, camera.incident, camera.pattern if camera.offsets else None


def site_fields(cp, sensor: SensorSpec, camera: MosaicCamera, e_in: np.ndarray | None = None) -> dict:
    """Angle -> ``(I_x, I_y, Re(E_x E_y*))`` (W/m^2 for unit incident intensity per polarisation, float32) on the
    frame sensor's grid shifted to that angle's pixels (one render when ``offsets`` is off)."""
    fs = camera.frame_sensor(sensor)
    X, Y = fs.coords()
    delta = INCIDENT[camera.incident]
    rot = None if delta is None else np.complex64(np.exp(-1j * np.deg2rad(delta)))
    out: dict = {}
    done: dict = {}
    with single_thread_blas():
        for ang, off in camera.offsets_of(sensor).items():
            if off in done:
                out[ang] = done[off]
                continue
            ix = np.zeros((fs.height_px, fs.width_px), np.float32)
            iy = np.zeros_like(ix)
            cr = np.zeros_like(ix)
            for k in range(1, 5):
                r, c = quadrant_slices(fs, k)
                amp = []
                for p, dest in ((0, ix), (1, iy)):
                    U, comp, scale = quadrant_transform(cp, p, X[c] + off[0], Y[r] + off[1], fs.quadrant_centre(k),
                                                        e_in)
                    dest[r, c] = (np.abs(U) ** 2 / comp**2 * scale).astype(np.float32)  # as quadrant_fields
                    amp.append(U / comp)
                if rot is not None:
                    cr[r, c] = (np.real(amp[0] * np.conj(amp[1]) * rot) * scale).astype(np.float32)
            done[off] = out[ang] = (ix, iy, cr)
    return out


def raw_of_sites(fields: dict, sensor: SensorSpec, camera: MosaicCamera) -> np.ndarray:
    """The raw mosaic ``(2H, 2W)`` (power per pixel) of :func:`site_fields`' fields: each pixel's polariser,
    the pattern, the crosstalk (cameras that differ only in those share one render of the fields)."""
    area = np.float32((camera.pitch(sensor) / sensor.magnification) ** 2)
    imgs = {a: polariser_intensity(*fields[a], a, camera.transmission, camera.extinction_ratio) * area
            for a in ANGLES}
    return pixel_crosstalk(interleave(imgs, camera.pattern), camera.crosstalk)


def render_raw(cp, sensor: SensorSpec, camera: MosaicCamera, e_in: np.ndarray | None = None) -> np.ndarray:
    """The noise-free raw mosaic ``(2H, 2W)`` (power per pixel, float32) of the incident field ``e_in`` on the
    pupil grid (None: a flat unit plane wave)."""
    return raw_of_sites(site_fields(cp, sensor, camera, e_in), sensor, camera)


def camera_frames(cp, sensor: SensorSpec, camera: MosaicCamera, e_in: np.ndarray | None = None) -> np.ndarray:
    """Noise-free demosaicked frames ``(2, H, W)`` of the camera (on :meth:`MosaicCamera.frame_sensor`)."""
    return camera.demosaic(render_raw(cp, sensor, camera, e_in), sensor)
