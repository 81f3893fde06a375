"""Wind and the temporal statistics of a turbulent path: per-screen wind (:class:`Wind`, the recipe's
``[wind]`` section through :func:`wind_of`), the Greenwood frequency, the coherence time tau0 and the
temporal PSDs of one pupil point's phase and of the pupil's tilt (theory, SI units throughout).

Per-screen turbulence strength comes from the screens' own Fried parameters (``PathModel.r0_screens``):
a screen of Fried parameter ``r0_i`` is the plane-wave phase of a slab with
``r0_i^(-5/3) = 0.423 k^2 Cn2_i dz_i``, so ``Cn2_i dz_i = r0_i^(-5/3) / (0.423 k^2)`` (:func:`cn2_dz`):
exactly the strength the screens are drawn with (a screen with r0 = inf has none).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import integrate, special

from ..validation import ConfigError
from .path import Scenario, solve_path
from .screens import psd_mvk

__all__ = ["Wind", "wind_of", "cn2_dz", "greenwood_frequency", "coherence_time", "v53",
           "temporal_psd_theory", "tilt_cutoff", "temporal_summary"]

#: the recipe's speed range (m/s) and direction range (deg), named in the messages
SPEED_RANGE = (0.0, 200.0)
DIRECTION_RANGE = (-360.0, 360.0)


@dataclass(frozen=True)
class Wind:
    """One wind velocity per screen, ``velocities[i] = (vx, vy)`` in m/s in the screen's plane (x along the
    grid's second axis, y along its first; a direction of 0 deg blows towards +x, 90 deg towards +y)."""

    velocities: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        v = np.asarray(self.velocities, float)
        if v.ndim != 2 or v.shape[1] != 2 or not np.all(np.isfinite(v)):
            raise ConfigError("wind", f"expected one finite (vx, vy) pair per screen, got {self.velocities!r}")

    @classmethod
    def from_speeds(cls, speeds, directions_deg=0.0) -> "Wind":
        s = np.asarray(speeds, float)
        d = np.deg2rad(np.broadcast_to(np.asarray(directions_deg, float), s.shape))
        return cls(tuple((float(a * np.cos(b)), float(a * np.sin(b))) for a, b in zip(s, d)))

    @property
    def v(self) -> np.ndarray:
        """(n_screens, 2) velocities, m/s."""
        return np.asarray(self.velocities, float).reshape(-1, 2)

    @property
    def speeds(self) -> np.ndarray:
        return np.hypot(self.v[:, 0], self.v[:, 1])

    @property
    def n_screens(self) -> int:
        return len(self.velocities)


def _check_list(where: str, vals, n: int) -> np.ndarray:
    a = np.asarray(vals, float)
    if a.shape != (n,):
        raise ConfigError(where, f"expected {n} values (one per screen, path.n_screens = {n}), got {len(a)}")
    return a


def wind_of(sc: Scenario, section: dict) -> Wind:
    """The :class:`Wind` of a parsed ``[wind]`` section (SI values, keys as in the recipe; :mod:`.scenario`
    checks each value's range): either ``speed_m_s`` (constant, or a linear ramp to ``end_speed_m_s`` at the
    receiver; screen i at z_i from the source) with one ``direction_deg``, or per-screen ``speeds_m_s``
    and ``directions_deg`` (``path.n_screens`` values each)."""
    n = sc.n_screens
    speed, end = section.get("speed_m_s"), section.get("end_speed_m_s")
    speeds, dirs = section.get("speeds_m_s"), section.get("directions_deg")
    direction = section.get("direction_deg")
    if speeds is not None and (speed is not None or end is not None):
        raise ConfigError("wind.speeds_m_s", "give either speed_m_s (with end_speed_m_s) or speeds_m_s, not both")
    if dirs is not None and direction is not None:
        raise ConfigError("wind.directions_deg", "give either direction_deg or directions_deg, not both")
    if speeds is None:
        if speed is None:
            raise ConfigError("wind.speed_m_s", "missing; give speed_m_s (m/s, with an optional end_speed_m_s) "
                              "or speeds_m_s (one per screen)")
        end = speed if end is None else end
        speeds = speed + (end - speed) * sc.z / sc.length
    speeds = _check_list("wind.speeds_m_s", speeds, n)
    dirs = _check_list("wind.directions_deg", dirs, n) if dirs is not None else \
        np.full(n, 0.0 if direction is None else direction)
    return Wind.from_speeds(speeds, dirs)


def cn2_dz(r0_screens, wavelength: float) -> np.ndarray:
    """Per-screen ``Cn2_i dz_i`` (m^(1/3)) from the screens' Fried parameters (plane-wave slab relation
    ``r0^(-5/3) = 0.423 k^2 Cn2 dz``); 0 where r0 is infinite."""
    k = 2 * np.pi / wavelength
    r0 = np.asarray(r0_screens, float)
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(r0), r0 ** (-5 / 3), 0.0) / (0.423 * k * k)


def _weights(n: int, spherical: bool, z=None, length=None) -> np.ndarray:
    if not spherical:
        return np.ones(n)
    if z is None or length is None:
        raise ValueError("the spherical-wave weighting needs the screens' distances z (from the source) and L")
    return (np.asarray(z, float) / length) ** (5 / 3)


def _path(path, wind: Wind, spherical: bool, wavelength=None, z=None, length=None):
    """(Cn2 dz per screen, |v| per screen, wavelength, weights) of a Scenario (its solved path) or of an
    explicit array of ``Cn2_i dz_i``."""
    if isinstance(path, Scenario):
        sc = path
        cdz = cn2_dz(solve_path(sc).r0_screens, sc.wavelength)
        wavelength, z, length = sc.wavelength, sc.z, sc.length
    else:
        cdz = np.asarray(path, float)
        if wavelength is None:
            raise ValueError("wavelength is needed with an explicit Cn2 dz profile")
    speeds = wind.speeds
    if speeds.shape != cdz.shape:
        raise ConfigError("wind", f"expected {cdz.size} velocities (one per screen), got {speeds.size}")
    return cdz, speeds, wavelength, _weights(cdz.size, spherical, z, length)


def greenwood_frequency(path, wind: Wind, *, wavelength: float | None = None, spherical: bool = False,
                        z=None, length: float | None = None) -> float:
    """Greenwood frequency (Hz) ``f_G = 2.31 lambda^(-6/5) [sum_i w_i Cn2_i dz_i |v_i|^(5/3)]^(3/5)``.

    ``path``: a :class:`~.path.Scenario` (its solved per-screen r0 give ``Cn2_i dz_i``, see
    :func:`cn2_dz`) or an array of ``Cn2_i dz_i`` (m^(1/3), then ``wavelength`` is needed).

    Path weighting: the plane-wave one by default (``w_i = 1``): the temporal statistics of the phase at
    one receiver point, which is what the screens themselves give (a screen at z seen from a point of the
    receiver through a point source's geometry is sampled at ``x z / L`` but still moves by ``v t``, so
    its temporal structure function is ``D_i(v_i tau)``, unweighted).  ``spherical=True``: the
    conventional spherical-wave form with ``w_i = (z_i / L)^(5/3)``, z from the source (pass ``z`` and
    ``length`` with an explicit profile), the weighting of the spherical-wave r0 (Eq. S3).
    Equivalently ``f_G = 0.427 v_5/3 / r0`` with the r0 and :func:`v53` of the same weighting."""
    cdz, s, lam, w = _path(path, wind, spherical, wavelength, z, length)
    return float(2.31 * lam ** (-6 / 5) * np.sum(w * cdz * s ** (5 / 3)) ** (3 / 5))


def v53(path, wind: Wind, *, spherical: bool = False, wavelength=None, z=None, length=None) -> float:
    """The turbulence-weighted wind speed ``v_5/3 = [sum w Cn2 dz |v|^(5/3) / sum w Cn2 dz]^(3/5)`` (m/s)."""
    cdz, s, _, w = _path(path, wind, spherical, wavelength or 1.0, z, length)
    tot = np.sum(w * cdz)
    return float((np.sum(w * cdz * s ** (5 / 3)) / tot) ** (3 / 5)) if tot > 0 else 0.0


def coherence_time(path, wind: Wind, *, spherical: bool = False, wavelength: float | None = None,
                   z=None, length: float | None = None) -> float:
    """Coherence time ``tau0 = 0.314 r0 / v_5/3`` (s), r0 and :func:`v53` with the same path weighting as
    :func:`greenwood_frequency` (plane wave by default: ``r0 = (0.423 k^2 sum Cn2 dz)^(-3/5)``); so that
    ``tau0 = 0.134 / f_G``.  Infinite without wind."""
    cdz, s, lam, w = _path(path, wind, spherical, wavelength, z, length)
    k = 2 * np.pi / lam
    tot = np.sum(w * cdz)
    if tot <= 0 or not np.any(s > 0):
        return float("inf")
    r0 = (0.423 * k * k * tot) ** (-3 / 5)
    v = (np.sum(w * cdz * s ** (5 / 3)) / tot) ** (3 / 5)
    return float(0.314 * r0 / v) if v > 0 else float("inf")


def tilt_cutoff(v: float, D: float, n: int = 1) -> float:
    """Conan et al. (1995) cut-off between a Zernike radial order n's low-frequency ``f^(-2/3)`` (tilt;
    ``f^0`` above) and high-frequency ``f^(-17/3)`` regimes: ``~0.3 (n + 1) v / D`` (Hz)."""
    return 0.3 * (n + 1) * v / D


def temporal_psd_theory(f, r0, v, *, mode: str = "phase", D: float | None = None,
                        scales: tuple[float, float] = (0.0, np.inf), axis: str = "along") -> np.ndarray:
    """One-sided temporal PSD (rad^2 / Hz, f > 0) under frozen flow, summed over layers (``r0`` and ``v``
    arrays of one Fried parameter and speed per layer, or scalars).

    ``scales``: the inner and outer scales ``(l0, L0)`` (m) of the screens' modified von Karman PSD.
    ``mode="phase"``: the phase at one pupil point.  Kolmogorov (``l0 = 0``, ``L0 = inf``):
    ``0.0774 r0^(-5/3) v^(5/3) f^(-8/3)`` per layer; otherwise the modified von Karman PSD of the screens
    integrated across the wind, ``(2 / v) int PSD(f / v, ky) dky``.
    ``mode="tilt"``: the Zernike tilt coefficient (Noll normalisation, rad rms over a pupil of diameter
    ``D``) along (``axis="along"``) or across the wind: the same integral with the tilt filter
    ``|Q|^2 = 2 [2 J2(pi D k) / (pi D k)]^2 2 cos^2(phi)``: ``f^(-2/3)`` below :func:`tilt_cutoff` (along
    the wind; ``f^0`` across), ``f^(-17/3)`` above."""
    f = np.atleast_1d(np.asarray(f, float))
    r0s, vs = np.broadcast_arrays(np.atleast_1d(np.asarray(r0, float)), np.atleast_1d(np.asarray(v, float)))
    if mode not in ("phase", "tilt"):
        raise ValueError(f"mode: expected 'phase' or 'tilt', got {mode!r}")
    if mode == "tilt" and D is None:
        raise ValueError("the tilt PSD needs the pupil diameter D")
    l0, L0 = scales
    out = np.zeros_like(f)
    kolmogorov = mode == "phase" and l0 == 0 and not np.isfinite(L0)
    ky = np.geomspace(1e-6, 1e4, 4001)  # 1/m, one side (the integrand is even in ky)
    for r, vv in zip(r0s, vs):
        if not np.isfinite(r) or vv <= 0:
            continue
        if kolmogorov:
            out += 0.0774 * r ** (-5 / 3) * vv ** (5 / 3) * f ** (-8 / 3)
            continue
        for i, fi in enumerate(f):
            kx = fi / vv
            kk = np.hypot(kx, ky)
            g = psd_mvk(kk, r, l0 if l0 > 0 else 1e-12, L0)
            if mode == "tilt":
                x = np.pi * D * kk
                cos2 = (kx / kk) ** 2 if axis == "along" else (ky / kk) ** 2
                g = g * 2 * (2 * special.jv(2, x) / x) ** 2 * 2 * cos2
            out[i] += 2 / vv * 2 * integrate.simpson(g * ky, x=np.log(ky))
    return out


def temporal_summary(sc: Scenario, wind: Wind) -> dict:
    """The figures ``metadesign turbulence show`` prints for a recipe with ``[wind]``: f_G (Hz), tau0 (s)
    and v_5/3 (m/s) with the plane-wave path weighting, and f_G with the spherical-wave weighting."""
    return {"greenwood_hz": greenwood_frequency(sc, wind), "tau0_s": coherence_time(sc, wind),
            "v53_m_s": v53(sc, wind), "greenwood_spherical_hz": greenwood_frequency(sc, wind, spherical=True),
            "wind_speeds_m_s": [float(s) for s in wind.speeds]}
