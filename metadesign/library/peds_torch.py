"""The certified surrogate in torch: a batched, differentiable twin of the low-fidelity supercell solve
(issue #34), and the PEDS model built on it.

:func:`solve_symmetric_t` is :func:`metadesign.library.supercell.solve_layers` (symmetric sector solve,
Li's staircase rule) written over torch tensors: the rectangles' centres and widths are tensors, every
step from their Fourier coefficients (``w/L sinc(d w/L) exp(-2 pi i d c/L)``, analytic in the widths)
through the sector eigenproblems (``torch.linalg.eig``) and grcwa's S-matrix recursion to the 0th order
is differentiable, and a batch of structures solves as one batched eigenproblem per sector.  The
width-independent pieces (harmonic set, uniform layers, symmetry bases) come from the same grcwa set-up
the numpy solver uses, so the two agree to rounding (test), and the numpy solver is the reference of this
twin's values and, by finite differences, of its gradients.

:func:`peds_t_torch` is :func:`metadesign.library.peds.certified_t` through this twin:
``mean_i t_lib(w_i) + sum_k a_k [t_super(nG_k) - mean_i t_unit(w_i; matched nG_k)]`` with the library's
bilinear look-up in float64; its gradient with respect to the sixteen widths is what a gradient-based
compensation under the certified model needs.  The structure must be mirror-symmetric in x and y about
the cell centre (a 2 x 2 supercell or a unit cell is; :func:`metadesign.library.supercell.supercell_rects`).
Float64 / complex128 throughout (the low truncations' eigenproblems are small).  Kinks: Li's rule changes
its band structure where two pillars' edges cross, so the surrogate is continuous there but its gradient
is one-sided."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch

from ..validation import ValidationError
from .coupling_net import bilinear_t
from .peds import PedsModel
from .rcwa import Stack, Truncation, symmetry_bases
from .store import UnitCellLibrary
from .supercells import matched_unit_harmonics

__all__ = ["solve_symmetric_t", "supercell_t_torch", "unit_t_torch", "couplings_torch", "lpa_torch",
           "peds_t_torch"]

_C = torch.complex128


@lru_cache(maxsize=32)
def _setup(L: float, stack: Stack, n_harmonics: int, thicknesses: tuple[float, ...], truncation: Truncation):
    """The width-independent operators of a stack of patterned layers on lattice period ``L`` (cached):
    grcwa's harmonic set, its uniform substrate and superstrate, the symmetry bases."""
    import grcwa

    obj = grcwa.obj(int(n_harmonics), [1.0, 0.0], [0.0, 1.0], L / stack.wavelength, 0.0, 0.0, verbose=0)
    obj.Add_LayerUniform(0.0, stack.n_substrate**2)
    for t in thicknesses:
        obj.Add_LayerGrid(t / L, 1, 1)
    obj.Add_LayerUniform(0.0, stack.n_superstrate**2)
    obj.Init_Setup(Gmethod=0 if truncation is Truncation.CIRCULAR else 1)
    G = np.asarray(obj.G)
    if tuple(G[0]) != (0, 0):
        raise RuntimeError("grcwa harmonic ordering changed: G[0] is not the 0th order")
    nG = int(obj.nG)
    kx, ky = np.real(np.asarray(obj.kx)), np.real(np.asarray(obj.ky))
    jk = np.vstack([np.diag(-ky), np.diag(kx)])  # grcwa's MakeKPMatrix
    kkT = np.block([[np.diag(kx * kx), np.diag(kx * ky)], [np.diag(ky * kx), np.diag(ky * ky)]])
    bases = tuple(torch.from_numpy(U) for U in symmetry_bases(G))
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=_C)  # noqa: E731
    return dict(G=G, nG=nG, omega=float(np.real(obj.omega)), jk=t(jk), kkT=t(kkT), bases=bases,
                kp_uni=(t(obj.kp_list[0]), t(obj.kp_list[-1])), q_uni=(t(obj.q_list[0]), t(obj.q_list[-1])),
                thickness=tuple(float(np.real(x)) for x in obj.thickness_list),
                q_sub0=complex(obj.q_list[0][0]), q_sup0=complex(obj.q_list[-1][0]))


def _coeff(d: torch.Tensor, c: torch.Tensor, w: torch.Tensor, L: float) -> torch.Tensor:
    """:func:`metadesign.library.supercell._coeff` over a batch: ``d`` (M, M) orders, ``c``, ``w`` (...)
    -> (..., M, M)."""
    c, w = c[..., None, None], w[..., None, None]
    return ((w / L) * torch.sinc(d * w / L)).to(_C) * torch.exp(-2j * np.pi * d * c / L)


def _staircase(G: np.ndarray, L: float, rects: torch.Tensor, eps_p: float, eps_bg: float):
    """:func:`metadesign.library.supercell.staircase_permittivity` for a batch of rectangle sets ``rects``
    (B, k, 4: xc, yc, wx, wy).  Bands run between every pair of consecutive sorted edges (a zero-width
    band, where two edges coincide, contributes exactly nothing), each holding the rectangles whose span
    contains its middle."""
    m = torch.as_tensor(G[:, 0])
    n = torch.as_tensor(G[:, 1])
    dm = (m[:, None] - m[None, :]).to(torch.float64)
    dn = (n[:, None] - n[None, :]).to(torch.float64)
    nG = len(G)
    eye = torch.eye(nG, dtype=_C)
    xc, yc, wx, wy = rects.unbind(-1)
    ezz = eps_bg * eye + (eps_p - eps_bg) * (_coeff(dm, xc, wx, L) * _coeff(dn, yc, wy, L)).sum(1)

    def aniso(axis: int):
        # axis 1: bands in y, inverse rule along x (eps_xx); axis 0: the converse (eps_yy)
        c_b, w_b = (yc, wy) if axis == 1 else (xc, wx)  # the band direction
        c_s, w_s = (xc, wx) if axis == 1 else (yc, wy)  # the segments inside a band
        ords, dd, idx = (m, dn, m) if axis == 1 else (n, dm, n)
        mx = int(ords.abs().max())
        o = torch.arange(-mx, mx + 1, dtype=torch.float64)
        d1 = o[:, None] - o[None, :]
        edges, _ = torch.sort(torch.cat([c_b - w_b / 2, c_b + w_b / 2], -1), -1)  # (B, 2k)
        lo, hi = edges[:, :-1], edges[:, 1:]
        mid = ((lo + hi) / 2).detach()
        inside = ((c_b - w_b / 2).detach()[:, None, :] < mid[..., None]) & \
                 (mid[..., None] < (c_b + w_b / 2).detach()[:, None, :])  # (B, bands, k)
        seg = _coeff(d1, c_s[:, None, :].expand_as(inside), w_s[:, None, :].expand_as(inside), L)
        toe = (1.0 / eps_bg) * torch.eye(len(o), dtype=_C) + (1.0 / eps_p - 1.0 / eps_bg) * (
            seg * inside[..., None, None]).sum(2)  # (B, bands, M, M)
        A = torch.linalg.inv(toe) - eps_bg * torch.eye(len(o), dtype=_C)
        i = idx + mx
        band = _coeff(dd, (lo + hi) / 2, hi - lo, L)  # (B, bands, nG, nG)
        return eps_bg * eye + (A[:, :, i[:, None], i[None, :]] * band).sum(1)

    return aniso(1), aniso(0), ezz


def _smatrix(q_list, phi_list, kp_list, thickness):
    """grcwa's ``GetSMatrix(0, N-1, ...)`` over a batch: (S11, S21)."""
    B, s = q_list[1].shape[0], q_list[0].shape[-1]
    eye = torch.eye(s, dtype=_C).expand(B, s, s)
    S11, S12, S21, S22 = eye, torch.zeros_like(eye), torch.zeros_like(eye), eye
    for layer in range(len(q_list) - 1):
        nxt = layer + 1
        Q = torch.linalg.solve(phi_list[layer], phi_list[nxt])
        P1 = torch.diag_embed(q_list[layer]) @ torch.linalg.inv(kp_list[layer] @ phi_list[layer])
        P2 = kp_list[nxt] @ phi_list[nxt] @ torch.diag_embed(1.0 / q_list[nxt])
        P = P1 @ P2
        T11, T12 = 0.5 * (Q + P), 0.5 * (Q - P)
        d1 = torch.diag_embed(torch.exp(1j * q_list[layer] * thickness[layer]))
        d2 = torch.diag_embed(torch.exp(1j * q_list[nxt] * thickness[nxt]))
        inv = torch.linalg.inv(T11 - d1 @ S12 @ T12)
        S11n = inv @ d1 @ S11
        S12n = inv @ (d1 @ S12 @ T11 - T12) @ d2
        S21 = S21 + S22 @ T12 @ S11n
        S22 = S22 @ T12 @ S12n + S22 @ T11 @ d2
        S11, S12 = S11n, S12n
    return S11, S21


def solve_symmetric_t(layers, L: float, stack: Stack = Stack(), n_harmonics: int = 200,
                      truncation: Truncation = Truncation.CIRCULAR) -> torch.Tensor:
    """(B, 2) complex128 ``(t_x, t_y)`` of a batch of mirror-symmetric stacks ``layers`` = ``[(thickness
    m, rects (B, k, 4) m: xc, yc, wx, wy), ...]`` (bottom first) on lattice period ``L``:
    :func:`metadesign.library.supercell.solve_layers` (``symmetric=True``) in torch, differentiable in the
    rectangles."""
    thick = tuple(float(t) for t, _ in layers)
    S = _setup(float(L), stack, int(n_harmonics), thick, Truncation(truncation))
    nG, jk, omega = S["nG"], S["jk"], S["omega"]
    eps_p, eps_sup, eps_sub = stack.n_pillar**2, stack.n_superstrate**2, stack.n_substrate**2
    ops = []
    for _, rects in layers:
        exx, eyy, ezz = _staircase(S["G"], float(L), rects.to(torch.float64), eps_p, eps_sup)
        kp = omega**2 * torch.eye(2 * nG, dtype=_C) - jk @ torch.linalg.inv(ezz) @ jk.T
        zero = torch.zeros_like(exx)
        M = torch.cat([torch.cat([eyy, zero], -1), torch.cat([zero, exx], -1)], -2) @ kp - S["kkT"]
        ops.append((M, kp))
    B = ops[0][0].shape[0]
    out = []
    for j, U in enumerate(S["bases"]):
        Uc = U.to(_C)
        W = (U * U).T.to(_C)
        qs, phis, kps = [(W @ S["q_uni"][0]).expand(B, -1)], [], [(Uc.T @ S["kp_uni"][0] @ Uc).expand(B, -1, -1)]
        eye = torch.eye(U.shape[1], dtype=_C).expand(B, -1, -1)
        phis.append(eye)
        for M, kp in ops:
            lam, phi = torch.linalg.eig(Uc.T @ M @ Uc)
            q = torch.sqrt(lam)
            qs.append(torch.where(q.imag < 0, -q, q))
            phis.append(phi)
            kps.append(Uc.T @ kp @ Uc)
        qs.append((W @ S["q_uni"][1]).expand(B, -1))
        phis.append(eye)
        kps.append((Uc.T @ S["kp_uni"][1] @ Uc).expand(B, -1, -1))
        S11, _ = _smatrix(qs, phis, kps, S["thickness"])
        a0 = torch.zeros(2 * nG, dtype=_C)
        a0[nG if j == 0 else 0] = 1.0 if j == 0 else -1.0  # x-pol: Hy > 0; y-pol: Hx < 0
        aN = (S11 @ (Uc.T @ a0)) @ Uc.T  # (B, 2nG)
        # order 0 at normal incidence (kx = ky = 0): Ex = q Hy / (omega eps), Ey = -q Hx / (omega eps)
        h_t, h_i = (aN[:, nG], a0[nG]) if j == 0 else (-aN[:, 0], -a0[0])
        out.append((S["q_sup0"] / eps_sup) * h_t / ((S["q_sub0"] / eps_sub) * h_i))
    phase = np.exp(-1j * 2 * np.pi * stack.n_superstrate * sum(thick) / stack.wavelength)
    return torch.stack(out, -1) * phase


def supercell_t_torch(widths: torch.Tensor, stack: Stack = Stack(), n_harmonics: int = 800) -> torch.Tensor:
    """(B, 2) ``t`` of 2 x 2 supercells ``widths`` (B, 2, 2, 2) m (``[r, c] = (wx, wy)`` at ``x = c p``,
    ``y = r p``, as :func:`metadesign.library.supercell.solve_supercell`)."""
    p = stack.period
    w = widths.to(torch.float64).reshape(-1, 4, 2)
    cx = torch.tensor([0.0, p, 0.0, p], dtype=torch.float64).expand(len(w), 4)
    cy = torch.tensor([0.0, 0.0, p, p], dtype=torch.float64).expand(len(w), 4)
    rects = torch.stack([cx, cy, w[..., 0], w[..., 1]], -1)
    return solve_symmetric_t([(stack.height, rects)], 2 * p, stack, n_harmonics)


def unit_t_torch(widths: torch.Tensor, stack: Stack = Stack(), n_harmonics: int = 200) -> torch.Tensor:
    """(..., 2) ``t`` of unit cells with pillars ``widths`` (..., 2) m (the library's solve,
    :func:`metadesign.library.rcwa.solve_cell`, for its Li rule)."""
    w = widths.to(torch.float64)
    flat = w.reshape(-1, 1, 2)
    zero = torch.zeros_like(flat[..., 0])
    rects = torch.stack([zero, zero, flat[..., 0], flat[..., 1]], -1)
    t = solve_symmetric_t([(stack.height, rects)], stack.period, stack, n_harmonics)
    return t.reshape(*w.shape[:-1], 2)


def couplings_torch(widths: torch.Tensor, stack: Stack, harmonics) -> torch.Tensor:
    """(K, B, 2) the coupling ``t_super(nG_k) - mean_i t_unit(w_i; matched)`` of supercells ``widths``
    (B, 2, 2, 2) m at each requested supercell truncation in ``harmonics``
    (:func:`metadesign.library.peds.low_fidelity_couplings`, differentiable)."""
    out = []
    for h in harmonics:
        ns, nu = matched_unit_harmonics(int(h), stack)
        out.append(supercell_t_torch(widths, stack, ns) - unit_t_torch(widths, stack, nu).mean((1, 2)))
    return torch.stack(out)


def lpa_torch(lib: UnitCellLibrary, widths: torch.Tensor) -> torch.Tensor:
    """(B, 2) complex128: the mean of the four pillars' library ``t``, bilinear as
    :func:`metadesign.library.store.interpolate_t` (clamped to the grid), in float64."""
    gx, gy = torch.as_tensor(lib.wx, dtype=torch.float64), torch.as_tensor(lib.wy, dtype=torch.float64)
    tab = torch.as_tensor(np.stack([lib.t_x, lib.t_y], -1), dtype=_C)  # (nx, ny, 2)
    return bilinear_t(gx, gy, tab, widths).mean((1, 2))


def peds_t_torch(model: PedsModel, lib: UnitCellLibrary, widths: torch.Tensor) -> torch.Tensor:
    """(B, 2) complex128: the certified surrogate's ``t`` of supercells ``widths`` (B, 2, 2, 2) m
    (:func:`metadesign.library.peds.certified_t`, differentiable in the widths)."""
    if model.library_sha256 and model.library_sha256 != lib.identity:
        raise ValidationError(f"peds_t_torch: the model was calibrated against another library (sha256 "
                              f"{model.library_sha256[:12]}), not this one ({lib.identity[:12]})")
    if widths.ndim != 4 or tuple(widths.shape[1:]) != (2, 2, 2):
        raise ValidationError(f"peds_t_torch: widths must be (n, 2, 2, 2) metres, got {tuple(widths.shape)}")
    c = couplings_torch(widths, lib.stack, model.harmonics)
    a = torch.tensor([complex(x) for x in model.coef], dtype=_C)
    return lpa_torch(lib, widths) + torch.tensordot(a, c, dims=1)
