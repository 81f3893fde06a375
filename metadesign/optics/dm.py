"""Wavefront correctors for a closed loop: a zonal deformable mirror, a tip-tilt mirror and a modal corrector,
and a separate tip-tilt mirror ahead of either (:class:`TipTiltSplit`) (pure numpy, SI units).

Everything is in **phase radians** at the sensing wavelength: a command vector ``c`` (one entry per actuator or
mode) makes the correction phase ``surface(c) = sum_i c_i B_i`` on the received-field crop, ``B_i`` the i-th
influence function (a Gaussian peaking at 1 rad for the zonal mirror, a unit-RMS Zernike for the modal ones).
A reflective mirror's surface (m) is ``phase * lambda / (4 pi)``; the stroke limit ``stroke`` is in the same
phase radians (a surface stroke ``s`` m is ``4 pi s / lambda`` rad).  The loop convention is
``residual = disturbance - surface(c)``.

Geometry: the crop of an FFT-centred grid (:class:`metadesign.sensing.device.ReceiverCrop`: sample
coordinates ``crop.coords()``, the receiver aperture of diameter ``D`` centred on the grid's origin).

Zonal mirror: ``n_act`` actuators across the pupil diameter on a square grid of pitch ``d = D / (n_act - 1)``
(Fried geometry: the outer actuators of the middle row and column sit on the pupil's edge, as for a
Shack-Hartmann with ``n_act - 1`` lenslets across); actuators farther than ``D/2 + margin * d`` from the
centre are dropped.  Influence ``exp(ln(coupling) (r / d)^2)``: Gaussian, ``coupling`` at the neighbouring
actuator (``sigma = d / sqrt(-2 ln coupling)``, as hcipy's ``make_gaussian_influence_functions``), not
truncated; or a measured influence matrix given as an array (:meth:`DeformableMirror.measured`).

Fit: Tikhonov-regularised least squares over the mask's pixels,
``c = (B^T B + lambda I)^-1 B^T phi`` with ``lambda = regularisation * mean(diag(B^T B))`` (relative to one
actuator's own energy on the mask), precomputed once per mask: a call is one matrix-vector product.
"""

from __future__ import annotations

import numpy as np

from ..validation import ConfigError, check_int, check_number
from .propagation import cexp
from .zernike import zernike

__all__ = ["DeformableMirror", "LinearCorrector", "ModalDM", "TipTiltMirror", "TipTiltSplit", "gaussian_influence",
           "phase_of", "fitted_oracle", "ORACLE_ITERATIONS"]


def _crop_geometry(crop):
    """(coords (A,), aperture diameter) of a :class:`~metadesign.sensing.device.ReceiverCrop`."""
    return np.asarray(crop.coords(), float), float(crop.aperture)


class LinearCorrector:
    """A corrector whose phase is linear in its commands: ``surface(c) = c @ B`` (B: ``(n, A, A)`` rad per
    unit command), commands clipped to ``+- stroke``; :meth:`fit` by Tikhonov least squares on a mask.

    ``basis`` (n, A, A); ``aperture_mask`` (A, A) bool, the default mask of :meth:`fit`."""

    def __init__(self, basis: np.ndarray, aperture_mask: np.ndarray, stroke: float = np.inf,
                 regularisation: float = 1e-3):
        basis = np.asarray(basis)
        if basis.ndim != 3 or basis.shape[1] != basis.shape[2] or basis.shape[0] < 1:
            raise ConfigError("dm.influence", f"expected an (n, A, A) array, got shape {basis.shape}")
        if not np.all(np.isfinite(basis)):
            raise ConfigError("dm.influence", "has NaN or infinite values")
        mask = np.asarray(aperture_mask, bool)
        if mask.shape != basis.shape[1:]:
            raise ConfigError("dm.mask", f"expected shape {basis.shape[1:]}, got {mask.shape}")
        self.stroke = np.inf if stroke == np.inf else check_number("dm.stroke", stroke, 0, open_lo=True, unit="rad")
        self.regularisation = check_number("dm.regularisation", regularisation, 0)
        self.shape = basis.shape[1:]
        self.n = basis.shape[0]
        self.mask = mask
        self._B = np.ascontiguousarray(basis.reshape(self.n, -1), np.float32)  # (n, A*A)
        self._rec: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def n_commands(self) -> int:
        return self.n

    @property
    def influence(self) -> np.ndarray:
        """(n, A, A) rad per unit command (a view)."""
        return self._B.reshape(self.n, *self.shape)

    def clip(self, commands: np.ndarray) -> np.ndarray:
        """Commands limited to ``+- stroke`` (rad)."""
        c = np.asarray(commands)
        return np.clip(c, -self.stroke, self.stroke) if np.isfinite(self.stroke) else c

    def surface(self, commands: np.ndarray) -> np.ndarray:
        """Correction phase (rad, float32) on the crop, ``(..., A, A)``, of commands ``(..., n)`` (clipped)."""
        c = np.asarray(commands, np.float32)
        if c.shape[-1] != self.n:
            raise ConfigError("dm.commands", f"expected {self.n} commands, got {c.shape[-1]}")
        return (self.clip(c) @ self._B).reshape(*c.shape[:-1], *self.shape)

    def reconstructor(self, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(R (n, n_mask) float32, flat pixel indices of the mask): ``commands = R @ phase.ravel()[idx]``.
        Computed once per mask (float64 solve) and cached."""
        m = self.mask if mask is None else np.asarray(mask, bool)
        if m.shape != self.shape:
            raise ConfigError("dm.mask", f"expected shape {self.shape}, got {m.shape}")
        key = np.packbits(m).tobytes()
        if key not in self._rec:
            idx = np.flatnonzero(m)
            M = self._B[:, idx].astype(np.float64)  # (n, n_mask)
            G = M @ M.T
            lam = self.regularisation * float(np.mean(np.diag(G))) if len(idx) else 0.0
            R = np.linalg.solve(G + lam * np.eye(self.n), M) if len(idx) else np.zeros((self.n, 0))
            if len(self._rec) >= 8:
                self._rec.pop(next(iter(self._rec)))
            self._rec[key] = (np.ascontiguousarray(R, np.float32), idx)
        return self._rec[key]

    def fit(self, phase: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Commands ``(..., n)`` (float32, not clipped) whose surface best fits ``phase`` ``(..., A, A)`` on
        ``mask`` (default: the aperture), Tikhonov-regularised least squares."""
        R, idx = self.reconstructor(mask)
        p = np.asarray(phase, np.float32)
        flat = p.reshape(*p.shape[:-2], -1)[..., idx]
        return flat @ R.T

    def fitting_error(self, phase: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray | float:
        """RMS (rad) over ``mask`` of ``phase - surface(fit(phase))``, piston removed (per leading index)."""
        m = self.mask if mask is None else np.asarray(mask, bool)
        p = np.asarray(phase, np.float64)
        res = (p - self.surface(self.fit(p, m)))[..., m]
        res = res - res.mean(axis=-1, keepdims=True)
        rms = np.sqrt(np.mean(res * res, axis=-1))
        return float(rms) if rms.ndim == 0 else rms


def gaussian_influence(x: np.ndarray, positions: np.ndarray, pitch: float, coupling: float) -> np.ndarray:
    """(n, A, A) Gaussian influence functions ``exp(ln(coupling) |r - r_i|^2 / pitch^2)`` (1 at the actuator,
    ``coupling`` one pitch away) on the square grid of sample coordinates ``x`` (A,); ``positions`` (n, 2) as
    (x, y) m.  Separable: one outer product per actuator."""
    a = np.log(coupling) / pitch ** 2
    gx = np.exp(a * (x[None, :] - positions[:, 0:1]) ** 2)  # (n, A)
    gy = np.exp(a * (x[None, :] - positions[:, 1:2]) ** 2)
    return (gy[:, :, None] * gx[:, None, :]).astype(np.float32)


def _pupil(coords, aperture) -> tuple[np.ndarray, float, np.ndarray]:
    """(coords (A,) float, D, aperture mask (A, A)) of a pupil of diameter D centred on coordinate 0."""
    x = np.asarray(coords, float)
    D = check_number("dm.aperture", aperture, 0, open_lo=True, unit="m")
    return x, D, (x[None, :] ** 2 + x[:, None] ** 2) <= (D / 2) ** 2


class DeformableMirror(LinearCorrector):
    """Zonal continuous-face-sheet mirror: Gaussian influence functions on a square actuator grid of pitch
    ``D / (n_act - 1)`` (:meth:`measured`: a measured influence matrix in place of the Gaussians).
    ``coords`` (A,) are the crop's sample coordinates (m), ``aperture`` the pupil diameter D (m), centred on
    coordinate 0; ``positions`` (n, 2) the kept actuators' (x, y) (m)."""

    def __init__(self, coords: np.ndarray, aperture: float, n_act: int = 11, coupling: float = 0.15,
                 margin: float = 1.0, stroke: float = np.inf, regularisation: float = 1e-3):
        x, D, mask = _pupil(coords, aperture)
        self.n_act = check_int("dm.n_act", n_act, 2, 256)
        self.coupling = check_number("dm.coupling", coupling, 0, 1, open_lo=True, open_hi=True)
        self.margin = check_number("dm.margin", margin, 0, 10, unit="pitch")
        self.pitch = D / (n_act - 1)
        g = (np.arange(n_act) - (n_act - 1) / 2) * self.pitch
        X, Y = np.meshgrid(g, g)
        keep = np.hypot(X, Y) <= D / 2 + self.margin * self.pitch + 1e-9 * D
        self.positions = np.stack([X[keep], Y[keep]], -1)
        self.aperture, self.coords = D, x
        super().__init__(gaussian_influence(x, self.positions, self.pitch, self.coupling), mask, stroke,
                         regularisation)

    @classmethod
    def measured(cls, coords: np.ndarray, aperture: float, influence: np.ndarray, stroke: float = np.inf,
                 regularisation: float = 1e-3, positions: np.ndarray | None = None) -> DeformableMirror:
        """A mirror from a measured influence matrix ``influence`` (n, A, A), rad per unit command on the crop
        (``pitch``, ``coupling``, ``margin`` None; ``positions`` (n, 2) if known)."""
        x, D, mask = _pupil(coords, aperture)
        self = cls.__new__(cls)
        basis = np.asarray(influence, np.float32)
        self.n_act, self.coupling, self.margin, self.pitch = None, None, None, None
        self.positions = None if positions is None else np.asarray(positions, float)
        self.aperture, self.coords = D, x
        LinearCorrector.__init__(self, basis, mask, stroke, regularisation)
        return self

    @classmethod
    def for_crop(cls, crop, **kwargs) -> DeformableMirror:
        """The mirror on a received-field crop (:class:`~metadesign.sensing.device.ReceiverCrop`)."""
        x, D = _crop_geometry(crop)
        return cls(x, D, **kwargs)


def _zernike_on(x: np.ndarray, radius: float, modes, inside_only: bool) -> np.ndarray:
    """(len(modes), A, A) Noll Zernikes (unit RMS on the unit disk) on the square grid ``x`` (A,), pupil of
    ``radius`` centred on 0; zero outside it when ``inside_only`` (else the polynomials continue)."""
    r = np.hypot(x[None, :], x[:, None]) / radius
    th = np.arctan2(x[:, None] + 0 * x[None, :], x[None, :] + 0 * x[:, None])
    Z = np.stack([zernike(int(j), r, th) for j in modes])
    return np.where(r <= 1, Z, 0.0) if inside_only else Z


class ModalDM(LinearCorrector):
    """A modal corrector: commands are the coefficients (rad RMS over the pupil) of Noll Zernike modes
    ``2 .. n_modes + 1`` (tilts first, no piston) or of the explicit Noll indices ``modes``; zero outside the
    pupil."""

    _inside_only = True

    def __init__(self, coords: np.ndarray, aperture: float, n_modes: int = 20, modes=None,
                 stroke: float = np.inf, regularisation: float = 1e-9):
        x, D, mask = _pupil(coords, aperture)
        if modes is None:
            modes = range(2, 2 + check_int("dm.n_modes", n_modes, 1, 2000))
        self.modes = tuple(check_int("dm.modes", j, 1, 100000) for j in modes)
        self.aperture, self.coords = D, x
        super().__init__(_zernike_on(x, D / 2, self.modes, self._inside_only), mask, stroke, regularisation)

    @classmethod
    def for_crop(cls, crop, **kwargs) -> ModalDM:
        """The corrector on a received-field crop (:class:`~metadesign.sensing.device.ReceiverCrop`)."""
        x, D = _crop_geometry(crop)
        return cls(x, D, **kwargs)


class TipTiltMirror(ModalDM):
    """Tip-tilt: Noll 2 (x) and 3 (y) tilts, commands in rad RMS over the pupil (a tilt of ``a`` rad RMS is a
    phase slope of ``4 a / D`` rad/m); a plane over the whole crop."""

    _inside_only = False

    def __init__(self, coords: np.ndarray, aperture: float, stroke: float = np.inf, regularisation: float = 1e-9):
        super().__init__(coords, aperture, modes=(2, 3), stroke=stroke, regularisation=regularisation)


class TipTiltSplit(LinearCorrector):
    """A separate tip/tilt mirror ahead of the mirror ``dm`` (a :class:`DeformableMirror` or :class:`ModalDM`,
    anything with ``coords`` and ``aperture``): commands ``[tip, tilt, *dm's]``, the tip/tilt mirror's two
    (:class:`TipTiltMirror`: rad RMS over the pupil, its own ``stroke``, default unlimited) then the mirror's,
    each clipped to its own stroke; the surface is their sum.  :meth:`fit` splits a phase as a woofer-tweeter
    loop does: the tip/tilt mirror takes its least-squares tilt on the mask, the mirror its fit of the phase
    with that tilt removed (so the mirror's stroke goes to the higher orders):
    ``R = [R_tt; R_dm (I - T^T R_tt)]`` (``T`` the tilts on the mask), one matrix-vector product per call."""

    def __init__(self, dm: LinearCorrector, stroke: float = np.inf, regularisation: float = 1e-9):
        tt = TipTiltMirror(dm.coords, dm.aperture, stroke=stroke, regularisation=regularisation)
        super().__init__(np.concatenate([tt.influence, dm.influence]), dm.mask, np.inf, dm.regularisation)
        self.tip_tilt, self.mirror = tt, dm
        self.coords, self.aperture = dm.coords, dm.aperture
        self.limits = np.concatenate([np.full(tt.n, tt.stroke), np.full(dm.n, dm.stroke)]).astype(np.float32)

    def clip(self, commands: np.ndarray) -> np.ndarray:
        """Each mirror's commands limited to its own stroke (rad)."""
        c = np.asarray(commands)
        return np.clip(c, -self.limits, self.limits) if np.isfinite(self.limits).any() else c

    def reconstructor(self, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        m = self.mask if mask is None else np.asarray(mask, bool)
        if m.shape != self.shape:
            raise ConfigError("dm.mask", f"expected shape {self.shape}, got {m.shape}")
        key = np.packbits(m).tobytes()
        if key not in self._rec:
            r_tt, idx = self.tip_tilt.reconstructor(m)
            r_dm, _ = self.mirror.reconstructor(m)
            r_tt, r_dm = r_tt.astype(np.float64), r_dm.astype(np.float64)
            T = self.tip_tilt.influence.reshape(self.tip_tilt.n, -1)[:, idx].astype(np.float64)  # (2, n_mask)
            R = np.concatenate([r_tt, r_dm - (r_dm @ T.T) @ r_tt])
            if len(self._rec) >= 8:
                self._rec.pop(next(iter(self._rec)))
            self._rec[key] = (np.ascontiguousarray(R, np.float32), idx)
        return self._rec[key]


def phase_of(field: np.ndarray) -> np.ndarray:
    """The phase of ``field`` (zero outside the aperture) referenced to its piston: ``angle(u conj(sum u))``.
    The absolute phase drifts by radians (the outer scale, the wind); wrapped as it is, a 2 pi cut across the
    aperture is a fixed point of a mirror's fit and the loop stalls.  Referenced to the field's mean it wraps
    only where the field itself has a cut (branch points), not because of its piston."""
    u = np.asarray(field)
    return np.angle(u * np.conj(u.sum())).astype(np.float64)


#: fixed-point iterations of the mirror-fitted oracle
ORACLE_ITERATIONS = 8


def fitted_oracle(dm, field: np.ndarray, mask: np.ndarray, iterations: int = ORACLE_ITERATIONS) -> np.ndarray:
    """The mirror's best phase for ``field`` with no delay: the fit of a perfect sensor's measurement, iterated
    on the residual (a wrapped phase's 2 pi jumps shrink as the residual does: the loop of an ideal sensor with
    zero delay, gain 1, run to its fixed point)."""
    u = field * mask
    c = dm.fit(phase_of(u), mask)
    for _ in range(iterations - 1):
        c = c + dm.fit(phase_of(u * cexp(-dm.surface(c))), mask)
    return dm.surface(c)
