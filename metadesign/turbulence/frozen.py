"""Frozen flow: the screens of a path moving with the wind (Taylor's hypothesis), step by step.

Each screen is drawn once, at the start, on a *long screen*: a rectangle covering the whole run's sweep
of the ``n x n`` window in that screen's wind direction (plus a margin), with the same modified von
Karman PSD as :mod:`.screens` (r0 = 1 m template, scaled by ``r0_i^(-5/6)``).  A run never wraps: the
window at step ``j`` (``t = j dt``) samples the long screen at ``x - v_i t`` (the pattern moves with the
wind), and a step past the drawn run is refused in one line.  Sub-pixel positions come from a Fourier
phase ramp on a padded window (each axis in turn, after removing the line through the padded row's
ends so that its periodic extension is continuous; the line is shifted exactly), not from
interpolation, which would smooth the spectrum; integer positions are plain slices (exact).
The long screen is the bounding box of the sweep: along x or y it is ``n + |v| T / dx`` long and
``n + 35`` wide (256 x 12,000 float32 = 12 MB for 30 m at 2.5 mm), but an oblique wind needs the whole
box (30 m at 40 deg: 9,400 x 7,900 = 300 MB); the memory is checked before anything is drawn.

The long rectangle (``ny x nx``, ``nx >= ny``; a screen moving mostly along y is drawn transposed) is
the FFT screen of :mod:`.screens` with its low frequencies resampled, so that its statistics match
:func:`~.screens.structure_function_theory` along and across the long axis although its FFT cells are
``nx / ny`` times longer in fy than in fx (:func:`spectrum`):

* the 2-D FFT part, cells ``dfx x dfy``, those near the origin with their cell-integrated,
  ``|f|^2``-weighted PSD (as in :class:`~.screens.ScreenGrid`);
* a block around the origin (the rows ``|fy| <= 4.5 dfy`` and as wide in fx) resampled on about square
  cells ``dfx x ~dfx``: each of its rows of fy is a sum over its fx, added to the FFT after its y pass (an
  elongated cell near the origin would put its power in the wrong direction: 5-15 % anisotropy in the
  structure function);
* subharmonics: 3 x 3 cells tiling the block's central cell, five levels down, as in :mod:`.screens`.

The expected structure function of these modes (:func:`structure_function_expected`, exact) is within
1.5 % of the theory up to half the short side along both axes (test).

Boiling (a screen that also evolves in its own frame) is not modelled: the flow is purely frozen.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from ..determinism import single_thread_blas
from ..validation import ValidationError, check_int, check_memory, check_number
from .screens import ScreenGrid, psd_mvk
from .temporal import Wind

__all__ = ["FrozenFlow", "frozen_flow", "long_screen", "spectrum", "structure_function_expected", "fourier_shift",
           "window"]

PAD = 16  # pixels of padding on each side of a window for the Fourier shift (cropped afterwards)


def _cell_psd(fx, fy, cell: tuple[float, float], scales: tuple[float, float], sub: int = 8,
              cap: int = 256) -> np.ndarray:
    """Effective PSD (r0 = 1 m) of ``wx x wy`` cells centred on ``(fx, fy)``: ``int_cell PSD |f|^2 / (|f_c|^2
    wx wy)`` (:func:`metadesign.turbulence.screens._cell_psd` for rectangular cells: ``sub`` samples
    along the shorter side, proportionally more along the longer one); 0 at the origin."""
    (wx, wy), (l0, L0) = cell, scales
    fx, fy = np.broadcast_arrays(np.asarray(fx, float), np.asarray(fy, float))
    w = min(wx, wy)
    nx_, ny_ = (min(sub * int(np.ceil(d / w - 1e-9)), cap) for d in (wx, wy))
    sx = ((np.arange(nx_) + 0.5) / nx_ - 0.5) * wx
    sy = ((np.arange(ny_) + 0.5) / ny_ - 0.5) * wy
    acc = np.zeros(fx.shape)
    for b in sy:
        f2 = (fx[..., None] + sx) ** 2 + (fy[..., None] + b) ** 2
        acc += np.sum(psd_mvk(np.sqrt(f2), 1.0, l0, L0) * f2, axis=-1)
    fc2 = fx**2 + fy**2
    return acc / (nx_ * ny_) / np.where(fc2 > 0, fc2, np.inf)


def _amplitudes(fx, fy, cell: tuple[float, float], scales: tuple[float, float], near: float | None = None,
                sub_cap: int = 256) -> np.ndarray:
    """``sqrt(PSD_cell wx wy)`` (r0 = 1 m) of ``wx x wy`` cells centred on (fx, fy): cell-integrated where the
    PSD varies across the cell (``|fx|, |fy| <= near``, default ``4.5 max(wx, wy)``), the centre value
    elsewhere; 0 at the origin."""
    (wx, wy), (l0, L0) = cell, scales
    fx, fy = np.broadcast_arrays(np.asarray(fx, float), np.asarray(fy, float))
    f = np.hypot(fx, fy)
    psd = np.array(psd_mvk(np.where(f == 0, 1.0, f), 1.0, l0, L0))
    big = 4.5 * max(wx, wy) if near is None else near
    sel = (np.abs(fx) <= big) & (np.abs(fy) <= big)
    psd[sel] = _cell_psd(fx[sel], fy[sel], cell, scales, cap=sub_cap)
    psd[f == 0] = 0.0
    return np.sqrt(psd * wx * wy)


#: rows of the FFT rectangle (|m| <= BLOCK_ROWS, around fy = 0) whose cells near fx = 0 are resampled on
#: square cells (see :func:`spectrum`)
BLOCK_ROWS = 4


def spectrum(shape: tuple[int, int], dx: float, scales: tuple[float, float], levels: int = 5) -> dict:
    """The amplitudes (r0 = 1 m, rad) of a long screen's modes (``shape = (ny, nx)``, ``nx >= ny``;
    ``scales = (l0, L0)``, m; see the module's docstring):

    * ``"fft"``: (ny, nx) amplitudes of the FFT cells ``dfx x dfy`` (``fftfreq`` order), zero in the block;
    * the block ``|fy| <= (M + 1/2) dfy`` (M = :data:`BLOCK_ROWS`), ``|fx| <= (K + 1/2) dfx``, with K such
      that the block is about square in frequency: resampled on ``dfx x wy`` cells, ``wy ~ dfx``:
      ``"block_fy"`` (R,) row frequencies, ``"block_k"`` (2K + 1,) fx indices, ``"block"`` (R, 2K + 1)
      amplitudes (0 at the origin);
    * ``"sub"``: per subharmonic level, ``(fsx (3,), fsy (3,), amplitudes (3, 3) [iy, ix])`` of 3 x 3 cells
      tiling the block's central cell, ``levels`` levels down (the centre cell of the last: piston).

    Every cell near the origin carries its cell-integrated, ``|f|^2``-weighted PSD, as in
    :class:`~.screens.ScreenGrid`: with square cells, each mode then carries its cell's share of the
    small-separation structure function along x and along y alike."""
    ny, nx = shape
    dfx, dfy = 1.0 / (nx * dx), 1.0 / (ny * dx)
    M = min(BLOCK_ROWS, (ny - 1) // 2)
    K = min(int(np.ceil((M + 0.5) * dfy / dfx - 0.5)), (nx - 1) // 2)
    R = 2 * int(round((M + 0.5) * dfy / dfx - 0.5)) + 1  # odd: a row at fy = 0
    wy = (2 * M + 1) * dfy / R
    fx, fy = np.fft.fftfreq(nx, dx), np.fft.fftfreq(ny, dx)
    aspect = dfy / dfx
    amp = np.zeros((ny, nx))
    for r in range(ny):
        amp[r] = _amplitudes(fx, fy[r], (dfx, dfy), scales, near=2 * (M + 1) * dfy,
                             sub_cap=8 * min(int(np.ceil(aspect)), 4))
    rows = np.r_[0:M + 1, ny - M:ny] if M > 0 else np.array([0])
    cols = np.r_[0:K + 1, nx - K:nx] if K > 0 else np.array([0])
    amp[np.ix_(rows, cols)] = 0.0
    block_fy = (np.arange(R) - R // 2) * wy
    block_k = np.arange(-K, K + 1)
    block = _amplitudes(block_k[None, :] * dfx, block_fy[:, None], (dfx, wy), scales)
    sub = []
    for p in range(1, levels + 1):
        sx, sy = dfx / 3**p, wy / 3**p
        fsx, fsy = np.array([-1.0, 0.0, 1.0]) * sx, np.array([-1.0, 0.0, 1.0]) * sy
        sub.append((fsx, fsy, _amplitudes(fsx[None, :], fsy[:, None], (sx, sy), scales)))
    return {"fft": amp, "block_fy": block_fy, "block_k": block_k, "block": block, "sub": sub, "dfx": dfx}


def structure_function_expected(shape: tuple[int, int], dx: float, scales: tuple[float, float], r, levels: int = 5):
    """The ensemble structure function (r0 = 1 m) of :func:`long_screen` along x and along y at separations
    ``r`` (m), exactly, from its modes' amplitudes: ``sum 2 a^2 (1 - cos(2 pi f r))`` (each mode's real
    part has variance ``a^2``); compare with :func:`~.screens.structure_function_theory`."""
    ny, nx = shape
    sp = spectrum(shape, dx, scales, levels)
    fx, fy = np.fft.fftfreq(nx, dx), np.fft.fftfreq(ny, dx)
    cells = [(fx[None, :], fy[:, None], sp["fft"]),
             (sp["block_k"][None, :] * sp["dfx"], sp["block_fy"][:, None], sp["block"])]
    cells += [(fsx[None, :], fsy[:, None], a) for fsx, fsy, a in sp["sub"]]
    r = np.atleast_1d(np.asarray(r, float))
    d = [[sum(float(np.sum(2 * a**2 * (1 - np.cos(2 * np.pi * (f1 if ax == 0 else f2) * rr)))) for f1, f2, a in cells)
          for rr in r] for ax in (0, 1)]
    return np.array(d[0]), np.array(d[1])


def long_screen(shape: tuple[int, int], dx: float, scales: tuple[float, float], seed, subharmonics: bool = True,
                levels: int = 5) -> np.ndarray:
    """One r0 = 1 m modified von Karman screen on an ``shape = (ny, nx)`` rectangle (float32, rad),
    ``nx >= ny``, inner and outer scales ``scales = (l0, L0)`` (m; see the module's docstring); ``seed`` an
    int or a SeedSequence.  Same seed, same bytes."""
    ny, nx = shape
    if nx < ny:
        raise ValueError("long_screen: nx >= ny (draw the transpose)")
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    rng_hf, rng_block, rng_sh = (np.random.default_rng(s) for s in ss.spawn(3))
    sp = spectrum(shape, dx, scales, levels if subharmonics else 0)
    with single_thread_blas():
        return _long_screen(ny, nx, dx, sp, rng_hf, rng_block, rng_sh)


def _long_screen(ny, nx, dx, sp, rng_hf, rng_block, rng_sh) -> np.ndarray:
    cn = np.empty((ny, nx), np.complex64)
    rng_hf.standard_normal(out=cn.view(np.float32), dtype=np.float32)
    cn *= sp["fft"].astype(np.float32)
    cn = sfft.ifft(cn, axis=0, overwrite_x=True)
    cn *= np.float32(ny)
    # the block's rows, summed over y for each of its fx: (ny, R) @ (R, 2K + 1), into the same columns
    y = np.arange(ny) * dx
    b = sp["block"]
    c = (rng_block.standard_normal(b.shape) + 1j * rng_block.standard_normal(b.shape)) * b
    E = np.exp(2j * np.pi * np.outer(y, sp["block_fy"]))
    cn[:, sp["block_k"] % nx] += (E @ c).astype(np.complex64)
    cn = sfft.ifft(cn, axis=1, overwrite_x=True)
    out = np.ascontiguousarray(cn.real) * np.float32(nx)
    if sp["sub"]:
        x = np.arange(nx) * dx
        L = len(sp["sub"])
        C = np.zeros((3 * L, 3 * L), np.complex128)
        ex, ey = [], []
        for i, (fsx, fsy, a) in enumerate(sp["sub"]):
            C[3 * i:3 * i + 3, 3 * i:3 * i + 3] = (rng_sh.standard_normal((3, 3))
                                                   + 1j * rng_sh.standard_normal((3, 3))) * a
            ex.append(np.exp(2j * np.pi * np.outer(fsx, x)))
            ey.append(np.exp(2j * np.pi * np.outer(fsy, y)))
        lo = (np.concatenate(ey).T @ (C @ np.concatenate(ex))).real  # sum of c[iy, ix] e^{2 pi i (fy y + fx x)}
        out += (lo - lo.mean()).astype(np.float32)
    return out


def fourier_shift(a: np.ndarray, shift: float, axis: int) -> np.ndarray:
    """``a`` sampled at ``k + shift`` along ``axis`` (band-limited: a phase ramp on its spectrum), after
    removing the line through the first and last samples (so that the periodic extension is continuous)
    and adding it back shifted exactly.  The edges ring (a wrap with a kink); crop them (:data:`PAD`).
    An odd length has no Nyquist bin, so every frequency keeps its amplitude."""
    a = np.moveaxis(np.asarray(a), axis, -1)
    dt = np.float32 if a.dtype == np.float32 else np.float64  # float32 in, float32 FFTs (~1e-6 rad)
    a = a.astype(dt, copy=False)
    m = a.shape[-1]
    k = np.arange(m, dtype=dt)
    slope = (a[..., -1:] - a[..., :1]) / dt(m - 1)
    line = a[..., :1] + slope * k
    spec = sfft.rfft(a - line, axis=-1)
    spec *= np.exp(2j * np.pi * np.fft.rfftfreq(m) * shift).astype(spec.dtype)
    out = sfft.irfft(spec, n=m, axis=-1) + line + slope * dt(shift)
    return np.moveaxis(out, -1, axis)


def window(screen: np.ndarray, y0: float, x0: float, n: int, pad: int = PAD) -> np.ndarray:
    """The ``n x n`` window of ``screen`` whose first sample is at the (sub-pixel) position ``(y0, x0)``
    (float32): a plain slice at integer positions, a Fourier shift (:func:`fourier_shift`) of a window
    padded by ``pad`` otherwise."""
    iy, fy = _split(y0)
    ix, fx = _split(x0)
    py, px = (pad if fy else 0), (pad if fx else 0)
    tail = 1 if n % 2 == 0 else 2  # an odd length along each shifted axis
    w = np.asarray(screen[iy - py:iy + n + py + (tail if fy else 0), ix - px:ix + n + px + (tail if fx else 0)])
    if not (fx or fy):
        return np.array(w, np.float32)
    if fx:
        w = fourier_shift(w, fx, axis=1)[:, px:px + n]
    if fy:
        w = fourier_shift(w, fy, axis=0)[py:py + n]
    return np.asarray(w, np.float32)


def _split(p: float) -> tuple[int, float]:
    """Integer and fractional parts of a position; within 1e-6 pixel of an integer, that integer."""
    r = round(p)
    if abs(p - r) < 1e-6:
        return int(r), 0.0
    i = int(np.floor(p))
    return i, p - i


class FrozenFlow:
    """The screens of one path under frozen flow for ``n_steps`` steps of ``dt`` seconds.

    ``grid``: the window's :class:`~.screens.ScreenGrid` (n, dx, inner and outer scales, subharmonics);
    ``r0_screens``: per-screen Fried parameters (inf: no turbulence, nothing drawn); ``wind``: one velocity
    per screen; ``seed``: an int or SeedSequence (one child per screen).  ``screens(j)`` is the
    ``(n_screens, n, n)`` float32 stack at ``t = j dt``: screen i is ``phi_i(x - v_i t)``.  The long
    screens are drawn at construction (memory checked first); the same seed gives the same bytes."""

    def __init__(self, grid: ScreenGrid, r0_screens, wind: Wind, dt: float, n_steps: int, seed, pad: int = PAD):
        r0s = np.asarray(r0_screens, float)
        self.dt = check_number("frozen flow dt", dt, 0, 1.0, open_lo=True, unit="s")
        self.n_steps = check_int("frozen flow n_steps", n_steps, 1, 10**8)
        if wind.n_screens != r0s.size:
            raise ValidationError(f"frozen flow: {wind.n_screens} wind velocities for {r0s.size} screens")
        self.grid, self.r0_screens, self.wind, self.pad = grid, r0s, wind, pad
        n, dx = grid.n, grid.dx
        self.step_px = wind.v * dt / dx  # (n_screens, 2): (x, y) pixels per step
        sweep = np.abs(self.step_px) * (n_steps - 1)
        live = [i for i, r in enumerate(r0s) if np.isfinite(r)]
        shapes = {}
        for i in live:
            ex, ey = (int(np.ceil(s - 1e-6)) for s in sweep[i])
            shapes[i] = (sfft.next_fast_len(n + 2 * pad + 2 + ey, real=True),
                         sfft.next_fast_len(n + 2 * pad + 2 + ex, real=True))
        px = [a * b for a, b in shapes.values()]
        need = 4 * sum(px) + 40 * max(px, default=0)  # the float32 screens + one draw's temporaries
        check_memory(f"frozen flow ({n_steps} steps of {dt:g} s)", need,
                     "shorten the run (n_steps or dt), lower the wind speeds or the grid size")
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        kids = ss.spawn(r0s.size)
        self.long: dict[int, np.ndarray] = {}
        self.start: dict[int, np.ndarray] = {}
        for i in live:
            ny, nx = shapes[i]
            if nx >= ny:
                s = long_screen((ny, nx), dx, (grid.l0, grid.L0), kids[i], grid.subharmonics)
            else:
                s = long_screen((nx, ny), dx, (grid.l0, grid.L0), kids[i], grid.subharmonics).T
            s *= np.float32(r0s[i] ** (-5 / 6))
            self.long[i] = s
            # window origin (y, x) at step 0: the pattern moves by +v t, so the origin moves by -v t
            self.start[i] = np.array([pad + (sweep[i, 1] if self.step_px[i, 1] > 0 else 0.0),
                                      pad + (sweep[i, 0] if self.step_px[i, 0] > 0 else 0.0)])

    @property
    def n_screens(self) -> int:
        return self.r0_screens.size

    @property
    def duration(self) -> float:
        """Seconds covered by the drawn run (the last step's time)."""
        return (self.n_steps - 1) * self.dt

    def origin(self, i: int, j: int) -> tuple[float, float]:
        """(y, x) position in screen i's long screen of the window's first sample at step j."""
        y0, x0 = self.start[i]
        return float(y0 - self.step_px[i, 1] * j), float(x0 - self.step_px[i, 0] * j)

    def screens(self, j: int) -> np.ndarray:
        """The (n_screens, n, n) float32 screens at ``t = j dt``."""
        if isinstance(j, (bool, np.bool_)) or not isinstance(j, (int, np.integer)) or not 0 <= j < self.n_steps:
            raise ValidationError(f"frozen flow: step {j!r} is outside the drawn run (steps 0..{self.n_steps - 1}, "
                                  f"t <= {self.duration:g} s); draw a FrozenFlow with more steps")
        n = self.grid.n
        out = np.zeros((self.n_screens, n, n), np.float32)
        for i, s in self.long.items():
            out[i] = window(s, *self.origin(i, int(j)), n, self.pad)
        return out

    def __len__(self) -> int:
        return self.n_steps

    def __iter__(self):
        return (self.screens(j) for j in range(self.n_steps))


def frozen_flow(tb, wind: Wind, dt: float, n_steps: int, seed) -> FrozenFlow:
    """The frozen flow of a :class:`~.propagate.Turbulence` (its grid and per-screen r0): its ``screens(j)``
    go straight into ``tb.element.forward(tb.source, ...)``."""
    return FrozenFlow(tb.grid, tb.path.r0_screens, wind, dt, n_steps, seed)
