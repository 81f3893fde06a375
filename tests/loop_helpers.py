"""Helpers shared by the loop tests (issue #50): a small frozen-flow world and loop.json's numbers."""

from __future__ import annotations

import json
from pathlib import Path


def loop_world(speed: float, steps: int, substeps: int = 2, seed: int = 3):
    """A 64 x 64, five-screen path at Rytov 0.2 with every screen moving at ``speed`` (m/s), ``steps`` frames of
    ``substeps`` sub-steps of 0.1 ms drawn from ``seed``: the loop's :class:`~metadesign.studies.loop.LoopWorld`."""
    from metadesign.reconstruction.dataset import received_crop
    from metadesign.reconstruction.losses import PiB
    from metadesign.studies.loop import LoopWorld
    from metadesign.turbulence.frozen import FrozenFlow
    from metadesign.turbulence.propagate import Turbulence
    from metadesign.turbulence.scenario import scenario_from_dict
    from metadesign.turbulence.temporal import Wind

    sc = scenario_from_dict({"path": {"n_screens": 5, "rytov": 0.2, "length_m": 1000.0},
                             "grid": {"n": 64, "spacing_mm": 5.0}, "receiver": {"aperture_cm": 10.0}})
    tb = Turbulence(sc, check=False).at_rytov(0.2, check=False)
    c0, a = received_crop(sc)
    flow = FrozenFlow(tb.grid, tb.path.r0_screens, Wind.from_speeds([speed] * sc.n_screens), 1e-4,
                      steps * substeps, seed)
    return LoopWorld(tb, flow.screens, c0, a, PiB(sc, c0, a))


def loop_numbers(out: Path) -> str:
    """loop.json without its timings, paths and provenance (what must not depend on how or on how many workers
    it ran)."""
    def strip(d):
        if isinstance(d, dict):
            return {k: strip(v) for k, v in d.items() if k not in ("seconds", "core_s_per_link_s", "figures", "recipe", "provenance")}
        if isinstance(d, list):
            return [strip(v) for v in d]
        return d

    return json.dumps(strip(json.loads((Path(out) / "loop.json").read_text())), sort_keys=True)
