"""Unit-cell RCWA for a rectangular pillar, on top of ``grcwa``.

Physics kernel only: pure functions over frozen dataclasses, SI units.

Conventions (see README "Conventions"):

* time dependence ``exp(-i omega t)`` (grcwa's own), fields ``exp(+i phi)``;
* light is incident from the substrate (z < 0) at normal incidence, the pillar
  occupies ``0 <= z <= h``, the superstrate (air) is ``z > h``;
* ``x-pol`` (the paper's "TE") has E along x, ``y-pol`` ("TM") has E along y;
* the complex transmission ``t`` is the 0th-order transmitted E field at the
  pillar-top plane ``z = h`` divided by the incident E field at ``z = 0``,
  multiplied by ``exp(-i k0 n_sup h)``: the same stack *without* a pillar
  therefore has ``t = 2 n_sub / (n_sub + n_sup)`` exactly (real, > 1 for glass
  into air).  ``T0 = (n_sup / n_sub) |t|^2`` is the 0th-order power
  transmittance.

Permittivity Fourier rule: Li's factorization for the rectangle (exact
rectangle Fourier coefficients; the x-normal field component ``Ex`` uses the
inverse rule along x and Laurent's rule along y, ``Ey`` the converse, ``Ez``
Laurent's rule in both).  The stock grid-FFT Laurent rule is available as
``Factorization.LAURENT`` for comparison only: it converges far too slowly at
this index contrast.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Stack",
    "Factorization",
    "Truncation",
    "SolverSettings",
    "CellResult",
    "solve_cell",
    "fabry_perot_t",
]


class Factorization(str, enum.Enum):
    """Fourier rule used for the pillar layer's permittivity."""

    LI = "li"
    LAURENT = "laurent"


class Truncation(str, enum.Enum):
    """Reciprocal-lattice truncation (grcwa ``Gmethod``)."""

    CIRCULAR = "circular"
    RECTANGULAR = "rectangular"


@dataclass(frozen=True)
class Stack:
    """Materials and geometry of the unit cell, SI units (metres)."""

    wavelength: float = 1.55e-6
    period: float = 0.7e-6
    height: float = 1.2e-6
    n_pillar: float = 3.48
    n_substrate: float = 1.444
    n_superstrate: float = 1.0

    def __post_init__(self) -> None:
        for name in ("wavelength", "period", "height", "n_pillar", "n_substrate", "n_superstrate"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a finite positive number, got {value!r}")


@dataclass(frozen=True)
class SolverSettings:
    """RCWA numerical settings. ``n_harmonics`` is the *requested* nG."""

    n_harmonics: int = 200
    truncation: Truncation = Truncation.CIRCULAR
    factorization: Factorization = Factorization.LI
    #: Solve the two mirror-symmetry sectors of the centred rectangle
    #: separately (exact at normal incidence, ~30x faster). ``False`` solves the
    #: full coupled problem, which also yields the (zero) cross-polarised terms
    #: numerically rather than by construction.
    use_symmetry: bool = True

    def __post_init__(self) -> None:
        if int(self.n_harmonics) < 1:
            raise ValueError(f"n_harmonics must be >= 1, got {self.n_harmonics!r}")


@dataclass(frozen=True)
class CellResult:
    """Result of one unit cell.

    ``jones[i, j]``: output polarisation i, input polarisation j (0 = x, 1 = y).
    Efficiencies are per *input* polarisation ``[x, y]``.
    """

    jones: np.ndarray  # (2, 2) complex
    T0: np.ndarray  # (2,) 0th-order transmittance
    T_total: np.ndarray  # (2,) all transmitted orders
    R_total: np.ndarray  # (2,) all reflected orders
    n_harmonics: int  # actual nG used (grcwa rounds down to a closed shell)

    @property
    def t_x(self) -> complex:
        return complex(self.jones[0, 0])

    @property
    def t_y(self) -> complex:
        return complex(self.jones[1, 1])


def fabry_perot_t(stack: Stack, n_layer: float) -> complex:
    """Analytic 0th-order ``t`` of a uniform layer of index ``n_layer`` filling
    the pillar region, in this module's convention (Airy / Fabry-Perot formula).
    """
    k0 = 2 * np.pi / stack.wavelength
    n0, n1, n2 = stack.n_substrate, n_layer, stack.n_superstrate
    r01, r12 = (n0 - n1) / (n0 + n1), (n1 - n2) / (n1 + n2)
    t01, t12 = 2 * n0 / (n0 + n1), 2 * n1 / (n1 + n2)
    delta = k0 * n1 * stack.height
    t = t01 * t12 * np.exp(1j * delta) / (1 + r01 * r12 * np.exp(2j * delta))
    return complex(t * np.exp(-1j * k0 * n2 * stack.height))


def _rect_coeff(m: np.ndarray, fill: float) -> np.ndarray:
    """Fourier coefficients of a centred indicator of relative width ``fill``."""
    return fill * np.sinc(m * fill)


def _inverse_rule_block(
    order_range: np.ndarray, fill: float, eps_in: float, eps_bg: float
) -> np.ndarray:
    """``inv(Toeplitz(1/eps)) - eps_bg * I`` along one axis inside the pillar band."""
    d = order_range[:, None] - order_range[None, :]
    toe = (1.0 / eps_bg) * (d == 0) + (1.0 / eps_in - 1.0 / eps_bg) * _rect_coeff(d, fill)
    return np.linalg.inv(toe) - eps_bg * np.eye(len(order_range))


def permittivity_matrices(
    G: np.ndarray, fx: float, fy: float, eps_p: float, eps_bg: float, factorization: Factorization
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Convolution matrices ``(eps_xx, eps_yy, eps_zz)`` of a centred rectangle
    of relative widths ``fx, fy`` over the harmonic set ``G`` (nG x 2 ints)."""
    m, n = G[:, 0], G[:, 1]
    dm = m[:, None] - m[None, :]
    dn = n[:, None] - n[None, :]
    cy = _rect_coeff(dn, fy)
    cx = _rect_coeff(dm, fx)
    delta = (dm == 0) & (dn == 0)
    eps_zz = eps_bg * delta + (eps_p - eps_bg) * cx * cy
    if factorization is Factorization.LAURENT:
        return eps_zz, eps_zz, eps_zz
    mx = int(np.abs(m).max())
    my = int(np.abs(n).max())
    ax = _inverse_rule_block(np.arange(-mx, mx + 1), fx, eps_p, eps_bg)
    ay = _inverse_rule_block(np.arange(-my, my + 1), fy, eps_p, eps_bg)
    # Ex: inverse rule along x inside the band |y| < wy/2, Laurent along y.
    eps_xx = eps_bg * delta + ax[m[:, None] + mx, m[None, :] + mx] * cy
    # Ey: inverse rule along y inside the band |x| < wx/2, Laurent along x.
    eps_yy = eps_bg * delta + ay[n[:, None] + my, n[None, :] + my] * cx
    return eps_xx, eps_yy, eps_zz


def _uniform_e_fields(hx, hy, kx, ky, q, omega, eps):
    """E (x, y) of plane-wave orders in a uniform medium from their H (x, y)."""
    hz = -(kx * hx + ky * hy) / q
    ex = (q * hy - ky * hz) / (omega * eps)
    ey = (kx * hz - q * hx) / (omega * eps)
    return ex, ey


def _flux(hx, hy, kx, ky, q, omega, eps):
    """z-directed Poynting flux per order (arbitrary common units)."""
    ex, ey = _uniform_e_fields(hx, hy, kx, ky, q, omega, eps)
    return 0.5 * np.real(ex * np.conj(hy) - ey * np.conj(hx))


def symmetry_bases(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal bases (2nG x k, real) of the (hx, hy) amplitude subspaces
    excited by x-pol and by y-pol light on a pillar with mirror symmetry in x
    and in y, at normal incidence.

    x-pol: Hy even in x and y, Hx odd in x and y.  y-pol: the converse.
    """
    nG = len(G)
    index = {(int(a), int(b)): i for i, (a, b) in enumerate(G)}
    seen: set[tuple[int, int]] = set()
    even_cols: list[dict[int, float]] = []
    odd_cols: list[dict[int, float]] = []
    for a, b in index:
        if (a, b) in seen:
            continue
        orbit = {(a, b), (-a, b), (a, -b), (-a, -b)}
        seen |= orbit
        if not orbit <= index.keys():
            raise RuntimeError("harmonic set is not mirror-symmetric")
        s = 1.0 / np.sqrt(len(orbit))
        even_cols.append({index[o]: s for o in orbit})
        if a != 0 and b != 0:
            odd_cols.append({index[o]: s * np.sign(o[0] * a) * np.sign(o[1] * b) for o in orbit})

    def basis(hx_cols, hy_cols):
        U = np.zeros((2 * nG, len(hx_cols) + len(hy_cols)))
        for c, col in enumerate(hx_cols):
            for i, v in col.items():
                U[i, c] = v
        for c, col in enumerate(hy_cols):
            for i, v in col.items():
                U[nG + i, len(hx_cols) + c] = v
        return U

    return basis(odd_cols, even_cols), basis(even_cols, odd_cols)


def _propagate(U, M, kp, kp_uni, q_uni, thickness, a0):
    """Eigen-solve the pillar layer restricted to span(U) and return the
    transmitted (aN) and reflected (b0) H amplitudes in the full basis, from
    one S-matrix (grcwa's GetSMatrix on the reduced operators)."""
    from grcwa import rcwa as _g

    Ut = U.T
    lam, phi = np.linalg.eig(Ut @ M @ U)
    q = np.sqrt(lam)
    q = np.where(np.imag(q) < 0.0, -q, q)  # grcwa's branch choice
    eye = np.eye(U.shape[1])
    # Uniform layers: q is constant on each symmetry orbit, so U^T diag(q) U
    # is diagonal with these entries.
    W = (U * U).T
    q_list = [W @ q_uni[0], q, W @ q_uni[1]]
    kp_list = [Ut @ kp_uni[0] @ U, Ut @ kp @ U, Ut @ kp_uni[1] @ U]
    S11, _S12, S21, _S22 = _g.GetSMatrix(0, 2, q_list, [eye, phi, eye], kp_list, thickness)
    a0r = Ut @ a0
    return U @ (S11 @ a0r), U @ (S21 @ a0r)


def solve_cell(
    wx: float,
    wy: float,
    stack: Stack = Stack(),
    settings: SolverSettings = SolverSettings(),
    *,
    allow_degenerate: bool = False,
) -> CellResult:
    """Solve one unit cell with a ``wx x wy`` pillar (metres) for both
    polarisations from a single eigen-solve and a single S-matrix.

    ``allow_degenerate`` admits ``w = 0`` (no pillar) and ``w = period``
    (uniform slab), which the library never uses but the analytic tests do.
    """
    import grcwa
    from grcwa import rcwa as _g

    p = stack.period
    lo_ok = (lambda w: w >= 0) if allow_degenerate else (lambda w: w > 0)
    hi_ok = (lambda w: w <= p) if allow_degenerate else (lambda w: w < p)
    for name, w in (("wx", wx), ("wy", wy)):
        if not np.isfinite(w) or not lo_ok(w) or not hi_ok(w):
            raise ValueError(
                f"{name} = {w * 1e6:.4g} um is outside (0, {p * 1e6:.4g}) um (the period)"
            )

    eps_sub = stack.n_substrate**2
    eps_sup = stack.n_superstrate**2
    eps_p = stack.n_pillar**2
    # Lengths in units of the period; grcwa: c = 1, freq = 1 / wavelength.
    obj = grcwa.obj(
        int(settings.n_harmonics),
        [1.0, 0.0],
        [0.0, 1.0],
        p / stack.wavelength,
        0.0,
        0.0,
        verbose=0,
    )
    obj.Add_LayerUniform(0.0, eps_sub)
    obj.Add_LayerGrid(stack.height / p, 1, 1)  # placeholder: eigensystem set below
    obj.Add_LayerUniform(0.0, eps_sup)
    obj.Init_Setup(Gmethod=0 if settings.truncation is Truncation.CIRCULAR else 1)
    G = np.asarray(obj.G)
    if tuple(G[0]) != (0, 0):  # grcwa sorts by |G|; the 0th order comes first
        raise RuntimeError("grcwa harmonic ordering changed: G[0] is not the 0th order")
    nG = int(obj.nG)

    exx, eyy, ezz = permittivity_matrices(
        G, wx / p, wy / p, eps_p, eps_sup, settings.factorization
    )
    epinv = np.linalg.inv(ezz)
    zero = np.zeros_like(exx)
    # grcwa's in-plane operator acts on (-Ey, Ex) -> (-Dy, Dx) (Liu's S4 form).
    ep2 = np.block([[eyy, zero], [zero, exx]])
    kp = _g.MakeKPMatrix(obj.omega, 1, epinv, obj.kx, obj.ky)
    kx, ky = obj.kx, obj.ky
    kkT = np.block([[np.diag(kx * kx), np.diag(kx * ky)], [np.diag(ky * kx), np.diag(ky * ky)]])
    M = ep2 @ kp - kkT  # grcwa's layer operator on (hx, hy), as in SolveLayerEigensystem
    kp_uni = [obj.kp_list[0], obj.kp_list[2]]
    q_uni = [obj.q_list[0], obj.q_list[2]]
    # Incident H amplitudes for both polarisations (columns):
    # x-pol (Ex > 0) has Hy > 0, y-pol (Ey > 0) has Hx < 0.
    a0 = np.zeros((2 * nG, 2), dtype=complex)
    a0[nG, 0] = 1.0
    a0[0, 1] = -1.0
    if settings.use_symmetry:
        aN = np.zeros_like(a0)
        b0 = np.zeros_like(a0)
        for j, U in enumerate(symmetry_bases(G)):
            aN[:, j : j + 1], b0[:, j : j + 1] = _propagate(
                U, M, kp, kp_uni, q_uni, obj.thickness_list, a0[:, j : j + 1]
            )
    else:
        eye = np.eye(2 * nG)
        aN, b0 = _propagate(eye, M, kp, kp_uni, q_uni, obj.thickness_list, a0)

    return zero_order_result(obj, a0, aN, b0, stack, stack.height)


def zero_order_result(obj, a0, aN, b0, stack: Stack, height: float) -> CellResult:
    """Jones matrix and efficiencies from the incident (``a0``), transmitted (``aN``) and reflected (``b0``)
    H amplitudes (2nG x 2, one column per input polarisation) of a solved grcwa stack whose first and last
    layers are the substrate and the superstrate; ``height``: the patterned layers' total thickness (the
    phase reference ``exp(-i k0 n_sup h)``)."""
    nG = int(obj.nG)
    kx, ky, omega = obj.kx, obj.ky, obj.omega
    eps_sub, eps_sup = stack.n_substrate**2, stack.n_superstrate**2
    q_sub = obj.q_list[0][:nG]
    q_sup = obj.q_list[-1][:nG]

    jones = np.zeros((2, 2), dtype=complex)
    T0 = np.zeros(2)
    T_tot = np.zeros(2)
    R_tot = np.zeros(2)
    phase_ref = np.exp(-1j * 2 * np.pi * stack.n_superstrate * height / stack.wavelength)
    for j in range(2):
        hx_i, hy_i = a0[:nG, j], a0[nG:, j]
        hx_t, hy_t = aN[:nG, j], aN[nG:, j]
        hx_r, hy_r = b0[:nG, j], b0[nG:, j]
        ex_i, ey_i = _uniform_e_fields(hx_i, hy_i, kx, ky, q_sub, omega, eps_sub)
        ex_t, ey_t = _uniform_e_fields(hx_t, hy_t, kx, ky, q_sup, omega, eps_sup)
        e_in = ex_i[0] if j == 0 else ey_i[0]
        jones[0, j] = ex_t[0] / e_in * phase_ref
        jones[1, j] = ey_t[0] / e_in * phase_ref
        f_in = _flux(hx_i, hy_i, kx, ky, q_sub, omega, eps_sub)[0]
        f_t = _flux(hx_t, hy_t, kx, ky, q_sup, omega, eps_sup) / f_in
        f_r = -_flux(hx_r, hy_r, kx, ky, -q_sub, omega, eps_sub) / f_in
        T0[j] = f_t[0]
        T_tot[j] = f_t.sum()
        R_tot[j] = f_r.sum()
    return CellResult(jones=jones, T0=T0, T_total=T_tot, R_total=R_tot, n_harmonics=nG)
