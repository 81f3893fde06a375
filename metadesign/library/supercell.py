"""RCWA beyond the single vertical pillar: stacks of rectangle layers (tapered pillars as slices) and
2 x 2 supercells of four different pillars (the local-periodic approximation's check).

The conventions are :mod:`metadesign.library.rcwa`'s (``exp(-i omega t)``, incidence from the substrate,
``t`` = 0th-order transmitted E at the top of the pillar layer over the incident E at its bottom, times
``exp(-i k0 n_sup h)``); a cell here has lattice period ``L`` (``p`` for a unit cell, ``2 p`` for a
supercell) and holds non-overlapping axis-aligned rectangles of the pillar index in the superstrate.

Permittivity Fourier rule for several rectangles (Li's rule for staircase structures): along y the
layer is cut into bands between consecutive rectangle edges; in each band the permittivity is piecewise
constant along x, so ``eps_xx`` takes the inverse rule along x band by band (``inv(Toeplitz(1/eps))``)
and Laurent's rule across the bands along y; ``eps_yy`` the converse; ``eps_zz`` Laurent's rule.  For one
centred rectangle this is exactly :func:`metadesign.library.rcwa.permittivity_matrices` (test).
Fourier coefficients: ``eps_G = (1/L^2) int eps(r) exp(-i G.r) d^2r``, element ``(G, G')`` = ``eps_{G - G'}``
(grcwa's convention)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rcwa import CellResult, SolverSettings, Stack, Truncation, symmetry_bases, zero_order_result

__all__ = ["Rect", "staircase_permittivity", "smatrix_11_21", "solve_layers", "solve_supercell", "solve_tapered",
           "supercell_rects", "taper_offsets", "tapered_layers", "patch_rects", "solve_patch"]


@dataclass(frozen=True)
class Rect:
    xc: float
    yc: float
    wx: float
    wy: float


def _coeff(d: np.ndarray, c: float, w: float, L: float) -> np.ndarray:
    """Fourier coefficients (orders ``d``) of the indicator of ``[c - w/2, c + w/2]`` on period ``L``."""
    return (w / L) * np.sinc(d * w / L) * np.exp(-2j * np.pi * d * c / L)


def _coeff_at(d: np.ndarray, c: float, w: float, L: float) -> np.ndarray:
    """:func:`_coeff` on an integer array ``d`` (the order differences of a convolution matrix), evaluated
    once per distinct order and indexed: the same numbers, without a sinc and an exponential per entry."""
    lo = int(d.min())
    return _coeff(np.arange(lo, int(d.max()) + 1), c, w, L)[d - lo]


def _inverse_axis(orders: np.ndarray, segs, L: float, eps_p: float, eps_bg: float) -> np.ndarray:
    """``inv(Toeplitz(1/eps)) - eps_bg I`` along one axis for pillar segments ``[(c, w), ...]``."""
    d = orders[:, None] - orders[None, :]
    toe = (1.0 / eps_bg) * (d == 0).astype(complex)
    for c, w in segs:
        toe = toe + (1.0 / eps_p - 1.0 / eps_bg) * _coeff(d, c, w, L)
    return np.linalg.inv(toe) - eps_bg * np.eye(len(orders))


def _bands(rects, L: float, axis: int):
    """Bands along ``axis`` (1: y) between consecutive rectangle edges, with the rectangles' segments
    along the other axis present in each: ``[(centre, width, [(c, w), ...]), ...]``."""
    lo = [(r.yc - r.wy / 2) if axis == 1 else (r.xc - r.wx / 2) for r in rects]
    hi = [(r.yc + r.wy / 2) if axis == 1 else (r.xc + r.wx / 2) for r in rects]
    edges = sorted(set(np.round(lo + hi, 15)))
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        mid = (a + b) / 2
        segs = [((r.xc, r.wx) if axis == 1 else (r.yc, r.wy)) for r, l, h in zip(rects, lo, hi) if l < mid < h]
        if segs:
            out.append(((a + b) / 2, b - a, segs))
    return out


def staircase_permittivity(G: np.ndarray, L: float, rects, eps_p: float, eps_bg: float):
    """Convolution matrices ``(eps_xx, eps_yy, eps_zz)`` over the harmonic set ``G`` (nG x 2 ints) of
    rectangles ``rects`` of permittivity ``eps_p`` in ``eps_bg``, cell ``[-L/2, L/2)^2``."""
    m, n = G[:, 0], G[:, 1]
    dm = m[:, None] - m[None, :]
    dn = n[:, None] - n[None, :]
    delta = (dm == 0) & (dn == 0)
    ezz = eps_bg * delta.astype(complex)
    for r in rects:
        ezz = ezz + (eps_p - eps_bg) * _coeff_at(dm, r.xc, r.wx, L) * _coeff_at(dn, r.yc, r.wy, L)
    mx, my = int(np.abs(m).max()), int(np.abs(n).max())
    exx = eps_bg * delta.astype(complex)
    for c, w, segs in _bands(rects, L, axis=1):  # bands in y, inverse rule along x
        A = _inverse_axis(np.arange(-mx, mx + 1), segs, L, eps_p, eps_bg)
        exx = exx + A[m[:, None] + mx, m[None, :] + mx] * _coeff_at(dn, c, w, L)
    eyy = eps_bg * delta.astype(complex)
    for c, w, segs in _bands(rects, L, axis=0):  # bands in x, inverse rule along y
        A = _inverse_axis(np.arange(-my, my + 1), segs, L, eps_p, eps_bg)
        eyy = eyy + A[n[:, None] + my, n[None, :] + my] * _coeff_at(dm, c, w, L)
    return exx, eyy, ezz


def solve_layers(layers, L: float, stack: Stack = Stack(), n_harmonics: int = 200,
                 truncation: Truncation = Truncation.CIRCULAR, symmetric: bool = False,
                 laurent: bool = False) -> CellResult:
    """0th-order Jones matrix and efficiencies of a stack of patterned layers ``[(thickness, [Rect, ...]),
    ...]`` (bottom first; their total thickness is the 'pillar height' of the phase reference) on lattice
    period ``L``.  ``symmetric``: every layer is mirror-symmetric in x and y about the cell centre (solve
    the two symmetry sectors separately, as the library does).  ``laurent``: Laurent's rule for every
    component (a check against grcwa's grid-FFT rule only: it converges far too slowly here)."""
    eps_sub, eps_sup, eps_p = stack.n_substrate**2, stack.n_superstrate**2, stack.n_pillar**2
    obj = _Cell(int(n_harmonics), L / stack.wavelength, truncation, [0.0] + [t / L for t, _ in layers] + [0.0],
                (eps_sub, eps_sup))
    G, nG = obj.G, obj.nG
    kx, ky, omega = obj.kx, obj.ky, obj.omega
    # each layer's eigenproblem M = [[eyy, 0], [0, exx]] kp - k k^T, with kp = omega^2 - Jk ezz^-1 Jk^T
    # (grcwa's MakeKPMatrix; Jk = [-diag(ky); diag(kx)]) built by blocks: diagonal scalings, no dense products
    # with the zero blocks.  Mirror symmetry in x and y (``symmetric``) makes every convolution matrix real
    # (the structure is even), so the sectors' eigenproblems are solved in real arithmetic.
    real = bool(symmetric)
    mirrors = _mirror_permutations(G) if real else None
    ops = []
    for _, rects in layers:
        exx, eyy, ezz = staircase_permittivity(G, L, rects, eps_p, eps_sup)
        if laurent:
            exx = eyy = ezz
        if real:
            for e in (exx, eyy, ezz):
                _check_mirrors(e, mirrors)
            exx, eyy, ezz = (_real_part(e) for e in (exx, eyy, ezz))
        ei = np.linalg.inv(ezz)
        kp = np.block([[-(ky[:, None] * ei * ky[None, :]), ky[:, None] * ei * kx[None, :]],
                       [kx[:, None] * ei * ky[None, :], -(kx[:, None] * ei * kx[None, :])]])
        kp[np.diag_indices(2 * nG)] += omega ** 2
        M = np.block([[eyy @ kp[:nG, :nG], eyy @ kp[:nG, nG:]], [exx @ kp[nG:, :nG], exx @ kp[nG:, nG:]]])
        M[:nG, :nG] -= np.diag(kx * kx)
        M[:nG, nG:] -= np.diag(kx * ky)
        M[nG:, :nG] -= np.diag(ky * kx)
        M[nG:, nG:] -= np.diag(ky * ky)
        ops.append((M, kp))
    kp_uni = [_real_part(k) if real else k for k in (obj.kp_list[0], obj.kp_list[-1])]
    q_uni = [obj.q_list[0], obj.q_list[-1]]
    a0 = np.zeros((2 * nG, 2), dtype=complex)
    a0[nG, 0] = 1.0  # x-pol: Hy > 0
    a0[0, 1] = -1.0  # y-pol: Hx < 0
    thick = obj.thickness_list

    def propagate(U, a):
        if U is None:  # the full problem: no change of basis
            def tr(m):
                return m
            qs, a_in = [q_uni[0]], a
        else:
            tr = _sector_projector(U, real)
            qs, a_in = [(U * U).T @ q_uni[0]], U.T @ a
        phis, kps = [np.eye(len(qs[0]))], [tr(kp_uni[0])]
        for M, kp in ops:
            lam, phi = np.linalg.eig(tr(M))
            q = np.sqrt(lam.astype(complex))
            qs.append(np.where(np.imag(q) < 0.0, -q, q))
            phis.append(phi)
            kps.append(tr(kp))
        qs.append(q_uni[1] if U is None else (U * U).T @ q_uni[1])
        phis.append(np.eye(len(qs[0])))
        kps.append(tr(kp_uni[1]))
        s11, s21 = smatrix_11_21(qs, phis, kps, thick, a_in)
        return (s11, s21) if U is None else (U @ s11, U @ s21)

    if symmetric:
        aN, b0 = np.zeros_like(a0), np.zeros_like(a0)
        for j, U in enumerate(symmetry_bases(G)):
            aN[:, j:j + 1], b0[:, j:j + 1] = propagate(U, a0[:, j:j + 1])
    else:
        aN, b0 = propagate(None, a0)
    return zero_order_result(obj, a0, aN, b0, stack, sum(t for t, _ in layers))


class _Cell:
    """The harmonic set and the two uniform half-spaces of a stack (the part of grcwa's ``obj`` the solve
    uses: ``G``, ``nG``, ``kx``, ``ky``, ``omega``, ``q_list``/``kp_list`` of the substrate and superstrate,
    ``thickness_list``), normal incidence, lengths in periods.  grcwa's own lattice and truncation
    (``Lattice_getG``: the same ``G`` in the same order); the uniform layers' ``q`` (grcwa's branch) and
    ``kp`` from their diagonal form instead of grcwa's dense products."""

    def __init__(self, n_harmonics: int, freq: float, truncation: Truncation, thickness: list[float],
                 eps_uniform: tuple[float, float]):
        from grcwa import rcwa as _g

        lk1, lk2 = _g.Lattice_Reciprocate([1.0, 0.0], [0.0, 1.0])
        G, nG = _g.Lattice_getG(int(n_harmonics), lk1, lk2, method=0 if truncation is Truncation.CIRCULAR else 1)
        self.G, self.nG = np.asarray(G), int(nG)
        if tuple(self.G[0]) != (0, 0):
            raise RuntimeError("grcwa harmonic ordering changed: G[0] is not the 0th order")
        self.kx, self.ky = _g.Lattice_SetKs(self.G, 0.0, 0.0, lk1, lk2)
        self.omega = 2 * np.pi * freq
        self.thickness_list = thickness
        kx, ky, w2 = self.kx, self.ky, self.omega ** 2
        self.q_list, self.kp_list = [], []
        for eps in eps_uniform:
            q = np.sqrt(eps * w2 - kx ** 2 - ky ** 2 + 0j)
            q = np.where(np.imag(q) < 0.0, -q, q)
            self.q_list.append(np.concatenate((q, q)))
            kp = np.block([[np.diag(w2 - ky * ky / eps), np.diag(kx * ky / eps)],
                           [np.diag(kx * ky / eps), np.diag(w2 - kx * kx / eps)]]).astype(complex)
            self.kp_list.append(kp)


def _mirror_permutations(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index permutations of the harmonic set ``G`` under the mirrors ``x -> -x`` and ``y -> -y``."""
    index = {(int(a), int(b)): i for i, (a, b) in enumerate(G)}
    try:
        return (np.array([index[(-int(a), int(b))] for a, b in G]), np.array([index[(int(a), -int(b))] for a, b in G]))
    except KeyError:
        raise RuntimeError("harmonic set is not mirror-symmetric") from None


def _check_mirrors(m: np.ndarray, mirrors) -> None:
    """A convolution matrix of a structure with the two mirror lines through the cell centre is invariant
    under both mirrors of the harmonics (what the sector solve assumes; inversion symmetry alone, which also
    makes it real, is not enough).  Tolerance 1e-6 of its largest entry: the band edges' rounding leaves
    ~1e-9 on periods off a round grid."""
    scale = float(np.abs(m).max()) or 1.0
    for P in mirrors:
        if float(np.abs(m[P][:, P] - m).max()) > 1e-6 * scale:
            raise ValueError("symmetric solve of a structure that is not mirror-symmetric about the cell centre")


def _real_part(m: np.ndarray) -> np.ndarray:
    """The real part of a convolution matrix of an even structure (its imaginary part is rounding, up to
    ~1e-9 of its largest entry)."""
    re, im = m.real, m.imag
    scale = max(float(re.max()), -float(re.min()), float(im.max()), -float(im.min())) or 1.0
    if max(float(im.max()), -float(im.min())) > 1e-6 * scale:
        raise ValueError("symmetric solve of a structure that is not mirror-symmetric about the cell centre")
    return np.ascontiguousarray(m.real)


def _sector_projector(U: np.ndarray, real: bool):
    """``m -> U^T m U`` for a symmetry basis ``U`` (2 nG x k, each column an orbit of <= 4 harmonics) as
    gathers: O(k nG) per matrix, not a dense product (``real``: the matrix's real part)."""
    k = U.shape[1]
    nz = [np.flatnonzero(U[:, j]) for j in range(k)]
    width = max(len(r) for r in nz)
    idx = np.zeros((k, width), np.int64)
    wts = np.zeros((k, width))
    for j, r in enumerate(nz):
        idx[j, :len(r)], wts[j, :len(r)] = r, U[r, j]

    def tr(m):
        m = np.asarray(m)
        if real and np.iscomplexobj(m):
            m = _real_part(m)
        rows = np.einsum("kw,kwn->kn", wts, m[idx])  # U^T m
        return np.einsum("kw,nkw->nk", wts, rows[:, idx])  # (U^T m) U
    return tr


def _is_eye(m: np.ndarray) -> bool:
    return m.shape[0] == m.shape[1] and np.array_equal(m, np.eye(m.shape[0]))


def smatrix_11_21(q_list, phi_list, kp_list, thickness_list, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(S11 @ a, S21 @ a)`` of a stack of layers (eigenvalues ``q``, eigenvectors ``phi``, ``kp`` matrices,
    thicknesses; bottom first) for incident amplitudes ``a`` (2 nG x k): grcwa's ``GetSMatrix`` recursion
    (Liu and Fan's, as in S4), rearranged: ``S11`` and ``S21`` feed only themselves, so they are carried as
    the columns ``a`` needs; the diagonal propagators scale rather than multiply; an identity ``phi`` (a
    uniform layer) is not inverted; the last interface's ``S12`` and ``S22`` are not formed.  The same
    algebra, to rounding (test: against ``GetSMatrix``), with about half the dense products."""
    s11, s21 = np.asarray(a, complex), np.zeros_like(a, dtype=complex)
    S12, S22 = None, None  # zero and identity until the first interface
    last = len(q_list) - 2
    for l in range(last + 1):
        ql, qn = np.asarray(q_list[l]), np.asarray(q_list[l + 1])
        phl, phn = phi_list[l], phi_list[l + 1]
        eye_l, eye_n = _is_eye(phl), _is_eye(phn)
        Q = phn if eye_l else (np.linalg.inv(phl) if eye_n else np.linalg.solve(phl, phn))
        kl = kp_list[l] if eye_l else kp_list[l] @ phl
        kn = kp_list[l + 1] if eye_n else kp_list[l + 1] @ phn
        P = (ql[:, None] * np.linalg.inv(kl)) @ (kn / qn[None, :])
        T11, T12 = 0.5 * (Q + P), 0.5 * (Q - P)
        d1, d2 = np.exp(1j * ql * thickness_list[l]), np.exp(1j * qn * thickness_list[l + 1])
        P1 = np.linalg.inv(T11 if S12 is None else T11 - (d1[:, None] * S12) @ T12)
        s11 = P1 @ (d1[:, None] * s11)
        s21 = s21 + (T12 @ s11 if S22 is None else S22 @ (T12 @ s11))
        if l < last:
            S12n = (P1 @ (-T12 if S12 is None else d1[:, None] * (S12 @ T11) - T12)) * d2[None, :]
            S22 = (T12 @ S12n + T11 * d2[None, :]) if S22 is None else \
                S22 @ (T12 @ S12n) + (S22 @ T11) * d2[None, :]
            S12 = S12n
    return s11, s21


def supercell_rects(widths, period: float):
    """The four pillars of a 2 x 2 supercell: ``widths[r][c] = (wx, wy)`` at ``x = c p``, ``y = r p`` (cell
    ``[-p, p)^2``, period ``2 p``; the pillars at ``p`` straddle the cell edge).

    Every line through a column (row) of pillar centres is a mirror line of the periodic array (the other
    column maps onto itself across the period), so centred on pillar (0, 0) the supercell is mirror-
    symmetric in x and y: no cross-polarisation, and the two symmetry sectors solve separately."""
    return patch_rects(np.asarray(widths, float).reshape(2, 2, 2), period)


def solve_supercell(widths, stack: Stack = Stack(), n_harmonics: int = 800,
                    truncation: Truncation = Truncation.CIRCULAR, symmetric: bool = True,
                    taper: tuple[float, int] | None = None) -> CellResult:
    """A 2 x 2 supercell (period ``2 p``) of four vertical pillars ``widths[r][c] = (wx, wy)`` (m).
    ``symmetric=False`` solves the full coupled problem (a check of the sector solve: ~4x slower).
    ``taper = (sidewall_deg, slices)``: the four pillars with sloped walls, ``widths`` at mid-height
    (:func:`taper_offsets`; the four stay mirror-symmetric, so the sector solve holds)."""
    _check_fit(widths, stack)
    if taper is None:
        return solve_layers([(stack.height, supercell_rects(widths, stack.period))], 2 * stack.period, stack,
                            n_harmonics, truncation, symmetric=symmetric)
    w = np.asarray(widths, float)
    layers = []
    for t, d in taper_offsets(stack.height, *taper):
        _check_fit(w + d, stack)
        layers.append((t, supercell_rects(w + d, stack.period)))
    return solve_layers(layers, 2 * stack.period, stack, n_harmonics, truncation, symmetric=symmetric)


def _check_fit(widths, stack: Stack) -> None:
    for wx, wy in np.asarray(widths, float).reshape(-1, 2):
        if not (0 < wx < stack.period and 0 < wy < stack.period):
            raise ValueError(f"pillar {wx * 1e6:.4g} x {wy * 1e6:.4g} um does not fit the period")


def patch_rects(widths, period: float):
    """The pillars of an ``m x m`` patch, ``widths[r][c] = (wx, wy)`` at ``x = c p``, ``y = r p`` (lattice
    period ``m p``; the patch repeats, so the pillars near the cell edge straddle it)."""
    w = np.asarray(widths, float)
    m = w.shape[0]
    return [Rect(c * period, r * period, float(w[r, c, 0]), float(w[r, c, 1])) for r in range(m) for c in range(m)]


def solve_patch(widths, stack: Stack = Stack(), n_harmonics: int = 1300,
                truncation: Truncation = Truncation.CIRCULAR) -> CellResult:
    """An ``m x m`` patch of vertical pillars (``widths`` (m, m, 2) m) repeated with period ``m p``: the full
    coupled problem (a patch cut from a design has no mirror symmetry), so cross-polarisation terms are
    computed, not assumed away."""
    w = np.asarray(widths, float)
    if w.ndim != 3 or w.shape[0] != w.shape[1] or w.shape[2] != 2:
        raise ValueError(f"widths must be (m, m, 2), got {w.shape}")
    _check_fit(w, stack)
    return solve_layers([(stack.height, patch_rects(w, stack.period))], w.shape[0] * stack.period, stack,
                        n_harmonics, truncation, symmetric=False)


def taper_offsets(height: float, sidewall_deg: float, slices: int) -> list[tuple[float, float]]:
    """``[(thickness, width offset), ...]`` (bottom first) of a pillar with sloped walls as ``slices`` layers of
    equal thickness: the width at height ``z`` is ``w + 2 (h/2 - z) / tan(angle)`` (``w`` is the width at
    mid-height: a 90 degree wall is the vertical pillar, and a taper keeps the pillar's volume); each slice
    takes the width at its own mid-height."""
    cot = 1.0 / np.tan(np.deg2rad(sidewall_deg))
    t = height / slices
    return [(t, 2 * (height / 2 - (k + 0.5) * t) * cot) for k in range(int(slices))]


def tapered_layers(wx: float, wy: float, height: float, sidewall_deg: float, slices: int):
    """A centred tapered pillar as layers (:func:`taper_offsets`)."""
    return [(t, [Rect(0.0, 0.0, wx + d, wy + d)]) for t, d in taper_offsets(height, sidewall_deg, slices)]


def solve_tapered(wx: float, wy: float, sidewall_deg: float, slices: int, stack: Stack = Stack(),
                  settings: SolverSettings = SolverSettings()) -> CellResult:
    """A unit cell with a tapered pillar (mirror-symmetric: the library's two-sector solve)."""
    layers = tapered_layers(wx, wy, stack.height, sidewall_deg, slices)
    for _, (r,) in layers:
        if not (0 < r.wx < stack.period and 0 < r.wy < stack.period):
            raise ValueError(f"the tapered pillar's width {min(r.wx, r.wy) * 1e6:.4g}-{max(r.wx, r.wy) * 1e6:.4g} "
                             f"um leaves (0, {stack.period * 1e6:.4g}) um")
    return solve_layers(layers, stack.period, stack, settings.n_harmonics, settings.truncation,
                        symmetric=settings.use_symmetry)
