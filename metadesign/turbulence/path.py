"""Turbulent path: Rytov number -> Cn^2 -> r0 -> per-screen r0 (Eqs. S2-S6),
and the sampling constraints of split-step simulation (Schmidt, Sec. 9.5).

Eqs. S2 and S5 as printed are not dimensionless (``[z_i (L - z_i)]^(5/6)``
carries m^(5/3)); the spherical-wave Rytov variance is
``sigma_chi^2 = 0.563 k^(7/6) sum_i Cn^2 [z_i (1 - z_i / L)]^(5/6) dz_i``
(Schmidt Eq. 9.64), used here with its S5 form
``1.33 k^(-5/6) sum_i r0_i^(-5/3) [z_i (1 - z_i / L)]^(5/6)``, where z_i is
measured from the source.  S3/S6 (spherical-wave r0, weight (z_i/L)^(5/3))
are used as printed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import lsq_linear

from ..validation import MEMORY_FRACTION, available_memory, check_int, check_number

__all__ = ["Scenario", "PathModel", "solve_path", "SamplingReport", "check_sampling"]


@dataclass(frozen=True)
class Scenario:
    wavelength: float = 1.55e-6
    length: float = 1000.0  # m, source to receiver
    n_screens: int = 13  # screens at z_i = linspace(0, L, n): first at the source, last at the receiver
    rytov: float = 0.3  # nominal spherical-wave log-amplitude variance
    max_screen_rytov: float = 0.1  # cap on each screen's own contribution
    inner_scale: float = 0.01  # m
    outer_scale: float = 100.0  # m
    n_grid: int = 256
    dx: float = 2.5e-3  # m, grid spacing (source and receiver: unscaled split step)
    receiver_aperture: float = 0.10  # m, telescope diameter D2
    metasurface_aperture: float = 5e-3  # m: the beam reducer images D2 onto this
    roi_factor: float = 4.0  # point-source illuminated region DROI = roi_factor * D2
    absorber_order: int = 16  # super-Gaussian boundary exp(-(r / (0.47 N dx))^order)
    subharmonics: bool = True

    def __post_init__(self) -> None:
        check_number("path.wavelength", self.wavelength, 100e-9, 20e-6, unit="m")
        check_number("path.length", self.length, 1.0, 1e6, unit="m")
        check_int("path.n_screens", self.n_screens, 3, 1000)
        check_number("path.rytov", self.rytov, 0, 5, open_lo=True)
        check_number("path.max_screen_rytov", self.max_screen_rytov, 0, 1, open_lo=True)
        check_number("path.inner_scale", self.inner_scale, 0, 1.0, open_lo=True, unit="m")
        check_number("path.outer_scale", self.outer_scale, 0, 1e5, open_lo=True, unit="m")
        check_int("grid.n", self.n_grid, 32, 8192)
        check_number("grid.spacing", self.dx, 0, 1.0, open_lo=True, unit="m")
        check_number("receiver.aperture", self.receiver_aperture, 0, 10.0, open_lo=True, unit="m")
        check_number("receiver.metasurface_aperture", self.metasurface_aperture, 0, 1.0, open_lo=True, unit="m")
        check_number("receiver.roi_factor", self.roi_factor, 1, 20)
        check_int("grid.absorber_order", self.absorber_order, 2, 64)

    @property
    def sample_bytes(self) -> int:
        """Planned peak memory of one sample: the float32 screens plus ~8 complex64 grids."""
        return int(self.n_grid**2 * (4 * self.n_screens + 8 * 8))

    def to_dict(self) -> dict:
        return {"path": {"wavelength_nm": self.wavelength * 1e9, "length_m": self.length,
                         "n_screens": self.n_screens, "rytov": self.rytov,
                         "max_screen_rytov": self.max_screen_rytov, "inner_scale_cm": self.inner_scale * 100,
                         "outer_scale_m": self.outer_scale},
                "grid": {"n": self.n_grid, "spacing_mm": self.dx * 1e3, "absorber_order": self.absorber_order,
                         "subharmonics": self.subharmonics},
                "receiver": {"aperture_cm": self.receiver_aperture * 100,
                             "metasurface_aperture_mm": self.metasurface_aperture * 1e3,
                             "roi_factor": self.roi_factor}}

    @property
    def k(self) -> float:
        return 2 * np.pi / self.wavelength

    @property
    def z(self) -> np.ndarray:
        return np.linspace(0.0, self.length, self.n_screens)

    @property
    def dz(self) -> float:
        return self.length / (self.n_screens - 1)

    @property
    def magnification(self) -> float:
        """Transverse magnification of the beam reducer (receiver -> metasurface)."""
        return self.metasurface_aperture / self.receiver_aperture


@dataclass(frozen=True)
class PathModel:
    cn2: float
    r0: float  # total spherical-wave r0 (Eq. S3)
    r0_screens: np.ndarray  # per screen (inf: no turbulence)
    rytov_screens: np.ndarray  # each screen's own log-amplitude variance
    rytov_achieved: float
    r0_achieved: float
    residual: dict = field(default_factory=dict)


def _weights(sc: Scenario):
    z, L = sc.z, sc.length
    w_chi = 1.33 * sc.k ** (-5 / 6) * (z * (1 - z / L)) ** (5 / 6)
    w_r0 = (z / L) ** (5 / 3)
    return w_chi, w_r0


def solve_path(sc: Scenario) -> PathModel:
    """Cn^2 from the Rytov number (S2, uniform Cn^2), total r0 (S3), then the
    per-screen ``x_i = r0_i^(-5/3) >= 0`` solving S5 and S6 as a bounded
    least-squares problem with each screen's Rytov capped at
    ``max_screen_rytov``; a weak pull towards the uniform-Cn^2 split picks one
    solution of the under-determined system."""
    z, L, k = sc.z, sc.length, sc.k
    dz = np.full(sc.n_screens, sc.dz)
    dz[[0, -1]] /= 2  # trapezoidal weights of the path integral
    cn2 = sc.rytov / (0.563 * k ** (7 / 6) * np.sum((z * (1 - z / L)) ** (5 / 6) * dz))
    r0 = (0.423 * k * k * cn2 * np.sum((z / L) ** (5 / 3) * dz)) ** (-3 / 5)
    w_chi, w_r0 = _weights(sc)
    x0 = 0.423 * k * k * cn2 * dz  # uniform split (S4)
    ub = np.where(w_chi > 0, sc.max_screen_rytov / np.maximum(w_chi, 1e-300), np.inf)
    ub = np.minimum(ub, 1e6 * x0.max() + 1.0)
    # a screen that neither Rytov nor r0 sees (the one on the point source) has no
    # observable effect: it gets no turbulence and is never drawn
    seen = (w_chi > 0) | (w_r0 > 0)
    b = np.array([sc.rytov, r0 ** (-5 / 3)])
    A = np.stack([w_chi, w_r0])
    A_s = A[:, seen] / b[:, None]  # relative residuals
    lam = 1e-3
    s = x0.max()
    m = int(seen.sum())
    A_aug = np.vstack([A_s * s, lam * np.eye(m)])
    b_aug = np.concatenate([np.ones(2), lam * x0[seen] / s])
    sol = lsq_linear(A_aug, b_aug, bounds=(np.zeros(m), ub[seen] / s), method="bvls")
    x = np.zeros(sc.n_screens)
    x[seen] = sol.x * s
    with np.errstate(divide="ignore"):
        r0s = np.where(x > 0, x ** (-3 / 5), np.inf)
    chi = A[0] @ x
    r0a = (A[1] @ x) ** (-3 / 5)
    return PathModel(cn2, r0, r0s, w_chi * x, float(chi), float(r0a),
                     {"rytov_rel": float(chi / sc.rytov - 1), "r0_rel": float(r0a / r0 - 1)})


@dataclass(frozen=True)
class SamplingReport:
    ok: bool
    constraints: dict
    failures: tuple[str, ...]


def check_sampling(sc: Scenario, pm: PathModel, c: float = 2.0) -> SamplingReport:
    """Schmidt's constraints (Eqs. 9.86-9.89) for an unscaled grid (dx at source
    and receiver), point source of illuminated region DROI, turbulence margin
    ``c lambda L / r0``."""
    lamL = sc.wavelength * sc.length
    d2 = sc.receiver_aperture
    droi = sc.roi_factor * d2
    d1 = lamL / droi  # point-source model width
    margin = c * lamL / pm.r0
    d1p, d2p = d1 + margin, d2 + margin
    dx, n = sc.dx, sc.n_grid
    cons = {
        "C1 dx <= lambda L / (D1' + D2')": (dx, lamL / (d1p + d2p)),
        "C2 N >= D1'/2dx + D2'/2dx + lambda L / 2dx^2": (d1p / (2 * dx) + d2p / (2 * dx) + lamL / (2 * dx * dx), n),
        "C4 dz <= dx^2 N / lambda": (sc.dz, dx * dx * n / sc.wavelength),
        "receiver aperture inside the absorber (D2 <= 0.6 N dx)": (d2, 0.6 * n * dx),
        "screen Rytov cap reaches the nominal Rytov": (sc.rytov, pm.rytov_achieved * (1 + 1e-3)),
        "memory per sample (GiB) within the available memory": (sc.sample_bytes / 2**30,
                                                                available_memory() * MEMORY_FRACTION / 2**30),
    }
    fails = []
    hints = {
        "C1": f"lower dx below {lamL / (d1p + d2p) * 1e3:.3g} mm or shorten the path",
        "C2": "raise n_grid or dx (C2 needs N >= "
              f"{int(np.ceil(d1p / (2 * dx) + d2p / (2 * dx) + lamL / (2 * dx * dx)))})",
        "C4": "use more screens or a larger grid",
        "receiver": "raise n_grid or dx",
        "screen": f"raise n_screens or max_screen_rytov (the cap allows {pm.rytov_achieved:.3g})",
        "memory": "lower grid.n or path.n_screens",
    }
    for name, (lhs, rhs) in cons.items():
        if lhs > rhs:
            fails.append(f"{name} fails ({lhs:.4g} > {rhs:.4g}): {hints[name.split()[0]]}")
    return SamplingReport(not fails, {k: [float(a), float(b)] for k, (a, b) in cons.items()}, tuple(fails))
