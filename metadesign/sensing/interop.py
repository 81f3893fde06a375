"""Fields in and out of the optics tools users already have (prysm, hcipy), as documented arrays.

metadesign's side is a :class:`SampledField`: a complex array ``(ny, nx)`` with its sample coordinates
``x``, ``y`` (metres, ascending, rows along +y) and, where known, the wavelength.  The coarse pupil of an
as-fabricated device is sampled at ``CoarsePupil.X`` on both axes; :func:`on_pupil` resamples any
input field onto that grid (bilinear in real and imaginary parts; zero outside the input's extent), which
is what :func:`~metadesign.sensing.render.render_psf` takes as ``field``.

* prysm (``prysm.propagation.Wavefront``): ``data`` complex, ``dx`` in mm, ``wavelength`` in um, an
  FFT-centred grid ``x = (i - n/2) dx``.
* hcipy (``hcipy.Field`` on a Cartesian grid): flat values with ``grid.separated_coords`` in metres.

Both libraries are optional: nothing here imports them until a conversion to their type is asked for.
Inputs are recognised by the module of their type (no attribute probing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..validation import ValidationError, check_finite_array
from .forward import CoarsePupil

__all__ = ["SampledField", "sampled", "on_pupil", "pupil_fields", "to_hcipy", "to_prysm"]


@dataclass(frozen=True)
class SampledField:
    """A complex field ``data`` (ny, nx) sampled at ``x`` (nx,) and ``y`` (ny,) metres (ascending; row i at
    ``y[i]``); ``wavelength`` in metres or None."""

    data: np.ndarray
    x: np.ndarray
    y: np.ndarray
    wavelength: float | None = None

    @property
    def dx(self) -> float:
        return float(self.x[1] - self.x[0]) if len(self.x) > 1 else float("nan")


def _kind(obj) -> str:
    mod = type(obj).__module__ or ""
    return "prysm" if mod.startswith("prysm") else "hcipy" if mod.startswith("hcipy") else "array"


def sampled(obj, dx: float | None = None, wavelength: float | None = None) -> SampledField:
    """A :class:`SampledField` from a prysm ``Wavefront``, an hcipy ``Field`` on a Cartesian grid, a
    :class:`SampledField`, or a complex numpy array with its pitch ``dx`` (m; centred grid
    ``x = (i - (n-1)/2) dx``)."""
    if isinstance(obj, SampledField):
        return obj
    kind = _kind(obj)
    if kind == "prysm":  # mm and um; FFT-centred
        data = np.asarray(obj.data)
        ny, nx = data.shape
        d = float(obj.dx) * 1e-3
        return SampledField(data, (np.arange(nx) - nx // 2) * d, (np.arange(ny) - ny // 2) * d,
                            float(obj.wavelength) * 1e-6)
    if kind == "hcipy":
        grid = obj.grid
        if not grid.is_separated or len(grid.dims) != 2:
            raise ValidationError("hcipy field: expected a 2-D separated Cartesian grid (make_pupil_grid)")
        xs, ys = (np.asarray(c, np.float64) for c in grid.separated_coords)
        return SampledField(np.asarray(obj).reshape(len(ys), len(xs)), xs, ys, wavelength)
    data = np.asarray(obj)
    if data.ndim != 2 or dx is None:
        raise ValidationError("field: expected a prysm Wavefront, an hcipy Field, or a 2-D array with its pitch dx")
    ny, nx = data.shape
    return SampledField(data, (np.arange(nx) - (nx - 1) / 2) * dx, (np.arange(ny) - (ny - 1) / 2) * dx, wavelength)


def _interp_matrix(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(len(dst), len(src)) linear interpolation weights; rows of points outside ``src`` are zero."""
    W = np.zeros((len(dst), len(src)))
    if len(src) == 1:
        W[np.isclose(dst, src[0]), 0] = 1.0
        return W
    j = np.clip(np.searchsorted(src, dst) - 1, 0, len(src) - 2)
    t = (dst - src[j]) / (src[j + 1] - src[j])
    inside = (t >= -1e-9) & (t <= 1 + 1e-9)
    rows = np.nonzero(inside)[0]
    W[rows, j[rows]] = 1 - t[rows]
    W[rows, j[rows] + 1] = t[rows]
    return W


def on_pupil(field, pupil: CoarsePupil, dx: float | None = None) -> np.ndarray:
    """The field resampled onto the coarse pupil grid of ``pupil`` ((N, N) complex64: ``render_psf``'s
    ``field``); bilinear, zero outside the input's extent.  A field whose wavelength is known must be at
    the device's (1 % tolerance)."""
    f = sampled(field, dx)
    check_finite_array("field", f.data)
    if f.wavelength is not None and abs(f.wavelength / pupil.wavelength - 1) > 0.01:
        raise ValidationError(f"field: wavelength {f.wavelength * 1e9:.1f} nm, the device's is "
                              f"{pupil.wavelength * 1e9:.1f} nm")
    X = np.asarray(pupil.X, np.float64)
    Wy, Wx = _interp_matrix(f.y, X), _interp_matrix(f.x, X)
    d = np.asarray(f.data, np.complex128)
    return (Wy @ d @ Wx.T).astype(np.complex64)


def pupil_fields(pupil: CoarsePupil) -> SampledField:
    """The as-fabricated pupil, documented: ``data`` (2, N, N) complex, the x- and y-polarised pupil
    fields (every channel summed) for a unit plane wave, sampled at ``pupil.X`` on both axes."""
    X = np.asarray(pupil.X, np.float64)
    return SampledField(np.asarray(pupil.G).sum(axis=1), X, X, pupil.wavelength)


def to_hcipy(f: SampledField):
    """An ``hcipy.Field`` (or a list of them for a stack) on the field's Cartesian grid."""
    import hcipy

    grid = hcipy.CartesianGrid(hcipy.SeparatedCoords([np.asarray(f.x), np.asarray(f.y)]))
    data = np.asarray(f.data)
    if data.ndim == 2:
        return hcipy.Field(data.ravel(), grid)
    return [hcipy.Field(d.ravel(), grid) for d in data]


def to_prysm(f: SampledField):
    """A ``prysm.propagation.Wavefront`` (dx in mm, wavelength in um) of a 2-D field on a uniform grid; for
    a stack (the pupil's two polarisations), a list of them, one per polarisation, as :func:`to_hcipy`
    returns (a Wavefront holds one 2-D field: prysm's ``plot2d`` and ``focus`` expect that)."""
    from prysm.propagation import Wavefront

    if f.wavelength is None:
        raise ValidationError("to_prysm: the field's wavelength is unknown")
    data = np.asarray(f.data)
    if data.ndim == 2:
        return Wavefront(data, f.wavelength * 1e6, f.dx * 1e3)
    return [Wavefront(np.asarray(d), f.wavelength * 1e6, f.dx * 1e3) for d in data]
