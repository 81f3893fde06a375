"""Supercell surrogates: one protocol (:class:`SupercellSurrogate`: ``t(widths)``, its torch twin ``t_torch``,
``pillar_terms``, ``card``, ``certify``) for every model of a 2 x 2 supercell's zeroth-order transmission,
implemented by the local-periodic approximation (:class:`LPA`), the coupling network (:class:`CouplingNet`)
and the certified PEDS surrogate (:class:`PEDS`), and one resolver, :func:`surrogate` (by name: ``"lpa"``,
``"coupling"`` / ``"supercell"``, ``"peds"``, or by model file).  Conventions: :mod:`.base`.

The models' kernels stay in their modules and are re-exported here: the numpy side of the coupling model
(:mod:`metadesign.library.coupling`), its network (:mod:`metadesign.library.coupling_net`, torch), the PEDS
model (:mod:`metadesign.library.peds`) and its torch twin (:mod:`metadesign.library.peds_torch`).  Every
name is imported on first use (PEP 562): importing this package imports no torch."""

from __future__ import annotations

import importlib

#: each name -> the module that defines it (relative to metadesign.library), imported on first use
_EXPORTS = {
    # the protocol, its implementations and the resolver
    "SupercellSurrogate": "surrogates.base", "Surrogate": "surrogates.base", "error_stats": "surrogates.base",
    "LPA": "surrogates.lpa", "CouplingNet": "surrogates.net", "PEDS": "surrogates.peds",
    "surrogate": "surrogates.registry", "register_surrogate": "surrogates.registry",
    "surrogate_names": "surrogates.registry", "canonical_name": "surrogates.registry",
    # the coupling model: numpy side (no torch) and the network (torch)
    "CouplingConfig": "coupling", "lpa_t": "coupling", "relative_error": "coupling", "save_coupling": "coupling",
    "tuple_t": "coupling", "coupling_card": "coupling", "is_coupling": "coupling",
    "transpose_supercells": "coupling", "Coupling": "coupling_net", "build_coupling": "coupling_net",
    "coupling_t": "coupling_net", "find_coupling": "coupling_net", "fit_coupling": "coupling_net",
    "load_coupling": "coupling_net", "pair_tables": "coupling_net", "pillar_terms": "coupling_net",
    # the certified supercell surrogate (cheap solves, calibrated; numpy)
    "PedsModel": "peds", "certified_t": "peds", "fit_peds": "peds", "find_peds": "peds", "load_peds": "peds",
    "save_peds": "peds", "low_fidelity_couplings": "peds", "peds_t": "peds",
    # its differentiable, batched torch twin
    "peds_t_torch": "peds_torch", "couplings_torch": "peds_torch", "solve_symmetric_t": "peds_torch",
    "lpa_torch": "peds_torch",
}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    mod = _EXPORTS.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"metadesign.library.{mod}"), name)


def __dir__():
    return sorted(_EXPORTS)
