"""The supercell coupling network (torch): :class:`Coupling` (structure and symmetries:
:mod:`metadesign.library.coupling`), its fit to solved supercells, its evaluation in batches and the
pair tables of a finite atom set.  The numpy side (configuration, cards, the LPA, look-ups) is
:mod:`metadesign.library.coupling`, which needs no torch."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..cards import load_weights, read_card
from ..validation import ValidationError
from .coupling import CARD_FORMAT, W0, WS, CouplingConfig, coupling_card
from .store import UnitCellLibrary

__all__ = ["Coupling", "bilinear_t", "build_coupling", "tu_tensor", "pillar_terms", "coupling_t", "load_coupling", "fit_coupling",
           "find_coupling", "pair_tables"]


class Coupling(nn.Module):
    """The coupling network of a library (see :mod:`metadesign.library.coupling` for its structure)."""

    def __init__(self, cfg: CouplingConfig, lib: UnitCellLibrary):
        super().__init__()
        self.cfg = cfg
        self.nets = nn.ModuleList()
        for _ in range(cfg.ensemble):
            mods, d = [], 24 if cfg.interaction == "environment" else 15
            for _ in range(cfg.layers - 1):
                mods += [nn.Linear(d, cfg.hidden), nn.SiLU()]
                d = cfg.hidden
            mods.append(nn.Linear(d, 2))
            self.nets.append(nn.Sequential(*mods))
        tab = np.stack([lib.t_x, lib.t_y], -1)  # (nx, ny, 2) complex
        self.register_buffer("gx", torch.tensor(lib.wx, dtype=torch.float64), persistent=False)
        self.register_buffer("gy", torch.tensor(lib.wy, dtype=torch.float64), persistent=False)
        self.register_buffer("tab", torch.tensor(np.stack([tab.real, tab.imag], -1), dtype=torch.float32),
                             persistent=False)  # (nx, ny, 2 pol, 2 re/im)

    def unit_t(self, widths):
        """Library ``t`` of each pillar, bilinear as :func:`metadesign.library.store.interpolate_t`:
        (n, 2, 2, 2 pol, 2 re/im); differentiable in the widths."""
        return bilinear_t(self.gx, self.gy, self.tab, widths)

    @staticmethod
    def features(widths, tu, pol: int):
        """(n, 2, 2, 6) per-pillar features for polarisation ``pol`` (y: the transposed supercell)."""
        u = (widths.to(torch.float32) - W0) / WS
        if pol == 0:
            return torch.cat([u, tu[..., 0, :], tu[..., 1, :]], -1)
        f = torch.cat([u.flip(-1), tu[..., 1, :], tu[..., 0, :]], -1)
        return f.transpose(1, 2)

    @staticmethod
    def environments(f):
        """(n, 4, 24) [f_i, f_H(i), f_V(i), f_D(i)] and (n, 4, 24) [f_i] * 4."""
        H, V, D = f.flip(2), f.flip(1), f.flip(1).flip(2)
        env = torch.cat([f, H, V, D], -1).reshape(f.shape[0], 4, 24)
        own = f.reshape(f.shape[0], 4, 6).repeat(1, 1, 4)
        return env, own

    def pillar_terms(self, widths, tu):
        """(n, 2, 2, 2 pol, 2 re/im): each pillar's coupling term ``G(env) - G(own)`` (the supercell's
        correction is their mean), at the pillar's own place ``[r, c]``."""
        out = []
        for pol in (0, 1):
            f = self.features(widths, tu, pol)
            if self.cfg.interaction == "environment":
                env, own = self.environments(f)
                x = torch.cat([env, own], 1)  # (n, 8, 24)
                g = sum(net(x) for net in self.nets) / len(self.nets)
                d = (g[:, :4] - g[:, 4:]).reshape(-1, 2, 2, 2)
            else:
                n = f.shape[0]
                fi = f.reshape(n, 4, 6)
                xs = []
                for kind, fj in enumerate((f.flip(2), f.flip(1), f.flip(1).flip(2))):
                    oh = torch.zeros(n, 4, 3, dtype=f.dtype)
                    oh[..., kind] = 1
                    xs += [torch.cat([fi, fj.reshape(n, 4, 6), oh], -1), torch.cat([fi, fi, oh], -1)]
                x = torch.cat(xs, 1)  # (n, 24, 15): [pair, own] for each kind
                g = sum(net(x) for net in self.nets) / len(self.nets)
                g = g.reshape(n, 3, 2, 4, 2)
                d = (g[:, :, 0] - g[:, :, 1]).sum(1).reshape(-1, 2, 2, 2)
            out.append(d if pol == 0 else d.transpose(1, 2))  # y: back from the transposed supercell
        return torch.stack(out, 3)

    def delta(self, widths, tu):
        """(n, 2 pol, 2 re/im) coupling correction."""
        return self.pillar_terms(widths, tu).mean((1, 2))

    def terms(self, widths: np.ndarray, t_units: np.ndarray, batch: int = 65536) -> np.ndarray:
        """numpy in and out: :func:`pillar_terms` of this model."""
        return pillar_terms(self, widths, t_units, batch)

    def tables(self, widths: np.ndarray, t_atoms: np.ndarray) -> np.ndarray:
        """numpy in and out: :func:`pair_tables` of this model."""
        return pair_tables(self, widths, t_atoms)

    def forward(self, widths, tu=None):
        """(n, 2 pol, 2 re/im) supercell ``t`` of widths (n, 2, 2, 2) m; ``tu`` the pillars' library ``t``
        (default: this model's bilinear look-up)."""
        if tu is None:
            tu = self.unit_t(widths)
        return tu.mean((1, 2)) + self.delta(widths, tu)


def bilinear_t(gx, gy, tab, widths):
    """``tab`` (nx, ny, ...) on the regular width grids ``gx``, ``gy`` (m, float64) looked up bilinearly at
    ``widths`` (..., 2) m, clamped to the grid as :func:`metadesign.library.store.interpolate_t`: (..., ...)
    in ``tab``'s dtype, differentiable in the widths (the weights in ``tab``'s real precision)."""
    w = widths.to(torch.float64)
    real = tab.real.dtype if tab.is_complex() else tab.dtype
    extra = (1,) * (tab.ndim - 2)

    def frac(v, g):
        f = ((v - g[0]) / (g[1] - g[0])).clamp(0, len(g) - 1)
        i0 = f.detach().floor().long().clamp(max=len(g) - 2)
        a = (f - i0).to(real)
        return i0, a.reshape(*a.shape, *extra)

    i, ax = frac(w[..., 0], gx)
    j, ay = frac(w[..., 1], gy)
    return ((1 - ax) * (1 - ay) * tab[i, j] + ax * (1 - ay) * tab[i + 1, j] + (1 - ax) * ay * tab[i, j + 1]
            + ax * ay * tab[i + 1, j + 1])


def build_coupling(cfg: CouplingConfig, lib: UnitCellLibrary):
    """A fresh (untrained) coupling model for library ``lib``."""
    return Coupling(cfg, lib)


def tu_tensor(t_units: np.ndarray):
    t = np.asarray(t_units)
    return torch.from_numpy(np.stack([t.real, t.imag], -1).astype(np.float32))


def pillar_terms(model, widths: np.ndarray, t_units: np.ndarray, batch: int = 65536) -> np.ndarray:
    """(n, 2, 2, 2 pol) complex64: each pillar's coupling term in its supercell; the pillar's effective
    transmission is its library ``t`` plus this, and the supercell's ``t`` their mean."""
    w = np.asarray(widths)
    out = np.empty((len(w), 2, 2, 2), np.complex64)
    with torch.no_grad():
        for a in range(0, len(w), batch):
            wt = torch.from_numpy(np.ascontiguousarray(w[a:a + batch], np.float64))
            r = model.pillar_terms(wt, tu_tensor(t_units[a:a + batch])).numpy()
            out[a:a + batch] = r[..., 0] + 1j * r[..., 1]
    return out


def coupling_t(model, widths: np.ndarray, t_units: np.ndarray | None = None, batch: int = 65536) -> np.ndarray:
    """(n, 2) complex64 supercell ``t`` of widths (n, 2, 2, 2) m, evaluated in batches without gradients;
    ``t_units`` (n, 2, 2, 2 pol) complex: the pillars' library ``t`` (as the as-fabricated model looked them
    up, e.g. with etch and sidewall), default the model's own look-up."""
    w = np.asarray(widths)
    out = np.empty((len(w), 2), np.complex64)
    with torch.no_grad():
        for a in range(0, len(w), batch):
            wt = torch.from_numpy(np.ascontiguousarray(w[a:a + batch], np.float64))
            tu = None if t_units is None else tu_tensor(t_units[a:a + batch])
            r = model(wt, tu).numpy()
            out[a:a + batch] = r[..., 0] + 1j * r[..., 1]
    return out


def load_coupling(path: str | Path, lib: UnitCellLibrary, check_library: bool = True):
    """The model at ``path`` (safetensors + card) for library ``lib`` (its sha256 must match the card's
    unless ``check_library`` is off); returns ``(model, card)``."""
    path, _, card = read_card(path, CARD_FORMAT, "coupling model")
    lib_card = card.get("library")
    if not isinstance(lib_card, dict) or not isinstance(lib_card.get("sha256"), str):
        raise ValidationError(f"{path}: the card's library entry is missing or not an object with a sha256")
    if check_library and lib.identity and lib.identity != lib_card["sha256"]:
        raise ValidationError(f"{path}: fitted against library {lib_card.get('path')} "
                              f"(sha256 {lib_card['sha256'][:12]}), not this one ({lib.identity[:12]})")
    try:
        cfg = CouplingConfig(**card["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValidationError(f"{path}: the card's config is not a coupling configuration ({exc})") from None
    model = Coupling(cfg, lib)
    state = load_weights(path, what="coupling model")
    try:
        model.load_state_dict(state)
    except RuntimeError:
        raise ValidationError(f"{path}: the weights do not fit the card's config (interaction "
                              f"{cfg.interaction!r}, hidden {cfg.hidden}, layers {cfg.layers}, ensemble "
                              f"{cfg.ensemble}): card and weights belong to different models") from None
    model.eval()
    return model, card


def fit_coupling(lib: UnitCellLibrary, widths: np.ndarray, t_ref: np.ndarray, cfg: CouplingConfig = CouplingConfig(),
                 *, steps: int = 4000, lr: float = 3e-3, weight_decay: float = 1e-5, val_fraction: float = 0.1,
                 seed: int = 0, log=lambda s: None) -> tuple[object, dict]:
    """Fit a coupling model to solved supercells ``widths`` (n, 2, 2, 2) m, ``t_ref`` (n, 2) complex.
    Full-batch Adam with a cosine schedule on the squared error in units of the pillars' rms ``|t|``; a
    seeded ``val_fraction`` of the rows picks the best step (none of the caller's held-out rows are
    passed here).  Deterministic for a seed (one thread)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n = len(widths)
    perm = rng.permutation(n)
    n_val = max(1, int(round(val_fraction * n))) if n >= 10 else 0
    va, tr = perm[:n_val], perm[n_val:]
    model = Coupling(cfg, lib)
    W = torch.from_numpy(np.ascontiguousarray(widths, np.float64))
    with torch.no_grad():
        tu = model.unit_t(W)
    T = torch.from_numpy(np.stack([t_ref.real, t_ref.imag], -1).astype(np.float32))
    scale = (tu ** 2).sum(-1).mean((1, 2)).sqrt()[..., None]  # (n, 2, 1) rms |t_i| per pol
    opt = torch.optim.Adam(model.nets.parameters(), lr=lr, weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    itr, iva = torch.from_numpy(tr), torch.from_numpy(va)

    def err(idx):
        p = model(W[idx], tu[idx])
        return ((p - T[idx]) ** 2).sum(-1).sqrt() / scale[idx][..., 0]

    best, best_state, hist = np.inf, None, []
    for s in range(steps):
        model.train()
        opt.zero_grad()
        loss = (err(itr) ** 2).mean()
        loss.backward()
        opt.step()
        sched.step()
        if s % 50 == 0 or s == steps - 1:
            with torch.no_grad():
                e_tr = float(err(itr).mean())
                e_va = float(err(iva).mean()) if n_val else e_tr
            hist.append((s, e_tr, e_va))
            if e_va < best:
                best = e_va
                best_state = {k: v.clone() for k, v in model.state_dict().items()}
            if s % 1000 == 0:
                log(f"    step {s}: train {e_tr:.4f}, val {e_va:.4f} (mean |dt| / rms|t_i|)")
    model.load_state_dict(best_state)
    model.eval()
    return model, {"steps": steps, "lr": lr, "weight_decay": weight_decay, "rows_fitted": len(tr),
                   "rows_validation": len(va), "best_validation_error": best,
                   "history": [list(h) for h in hist]}


def find_coupling(lib: UnitCellLibrary, path: str | Path | None = None):
    """``(model, card, path)``: the coupling model at ``path``, else the one fitted against ``lib``
    (:func:`~metadesign.library.coupling.coupling_card`)."""
    w = coupling_card(lib, path)
    m, card = load_coupling(w, lib)
    return m, card, w


def pair_tables(model, widths: np.ndarray, t_atoms: np.ndarray) -> np.ndarray:
    """For a pair model and a finite set of pillars (an atom table: widths (A, 2) m, library ``t`` (A, 2)):
    ``P[kind, pol, a, b]`` (3, 2, A, A) complex64, the term of pillar ``a`` from neighbour ``b`` in the
    supercell's frame (kind 0: the other pillar of its row, 1: of its column, 2: the diagonal one), so that
    any supercell of those pillars is a few look-ups (:func:`tuple_t`): a discretizer searches atom
    4-tuples without running the network."""
    if model.cfg.interaction != "pair":
        raise ValidationError(f"the coupling model has interaction {model.cfg.interaction!r}; pair tables (the "
                              "compensating discretizer, device-scale look-ups) need interaction 'pair'")
    A = len(widths)
    u = torch.from_numpy(((np.asarray(widths) - W0) / WS).astype(np.float32))
    t = np.asarray(t_atoms)
    tt = torch.from_numpy(np.stack([t.real, t.imag], -1).astype(np.float32))  # (A, 2 pol, 2)
    out = np.zeros((3, 2, A, A), np.complex64)
    with torch.no_grad():
        for pol in (0, 1):
            f = (torch.cat([u, tt[:, 0], tt[:, 1]], -1) if pol == 0
                 else torch.cat([u.flip(-1), tt[:, 1], tt[:, 0]], -1))  # (A, 6)
            for kind in range(3):
                oh = torch.zeros(A, A, 3)
                oh[..., kind] = 1
                fa, fb = f[:, None].expand(A, A, 6), f[None, :].expand(A, A, 6)
                own = torch.cat([fa, fa, oh], -1)
                pair = torch.cat([fa, fb, oh], -1)
                g = sum(net(pair) - net(own) for net in model.nets) / len(model.nets)
                # the y-polarised term was computed on the transposed supercell: its row is our column
                k_orig = kind if pol == 0 or kind == 2 else 1 - kind
                out[k_orig, pol] = (g[..., 0] + 1j * g[..., 1]).numpy()
    return out
