"""Stage 5: modified von Karman screens, Rytov path model, point-source split-step propagation, the
scenario recipe and its validation against theory (:mod:`.validate`), and one beacon sample through a
device to the sensor (:class:`.chain.BeaconChain`)."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562); a function named like its
#: module (``screens.screens``, ``validate.validate``) is reached through the module
_EXPORTS = {
    "BeaconChain": "chain", "BeaconSample": "chain", "PathModel": "path", "SamplingReport": "path",
    "Scenario": "path", "check_sampling": "path", "solve_path": "path", "Turbulence": "propagate",
    "point_source": "propagate", "split_step": "propagate", "split_step_torch": "propagate",
    "load_scenario": "scenario", "scenario_from_dict": "scenario", "ScreenGrid": "screens", "psd_mvk": "screens", "structure_function_theory": "screens",
    "FrozenFlow": "frozen", "frozen_flow": "frozen", "Wind": "temporal", "greenwood_frequency": "temporal", "coherence_time": "temporal",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

