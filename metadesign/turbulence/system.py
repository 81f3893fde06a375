"""One system factory (poppy's ``OpticalSystem`` built by one function per instrument): a layout, a sensing
recipe, a turbulence scenario and a fabrication section become the :class:`System` every consumer uses:
the as-fabricated device (library, supercell coupling, fab axes), the sensor, the perturbation, the coarse
pupil and the beacon chain through the turbulence.  The dataset build, the demo and the pipeline build
their systems here, so a coupling model, a fab library or a sensor tensor size means the same everywhere."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from ..library.store import load_library
from ..paths import resolve_against
from ..sensing.device import check_wavelengths
from ..sensing.model import AsFabricated, SensingRecipe, load_sensing_recipe
from ..sensing.transmission import Perturbation
from ..validation import ValidationError
from .chain import BeaconChain
from .path import Scenario
from .scenario import load_scenario

__all__ = ["System", "build_system"]


@dataclass
class System:
    """A device as made, its sensor and (optionally) the turbulence in front of it."""

    device: AsFabricated
    sensing: SensingRecipe
    scenario: Scenario | None = None
    perturbation: Perturbation = field(default_factory=Perturbation)

    def pupil(self, progress=None):
        """The coarse pupil of the device as made, at the sensor's distance and pupil grid."""
        return self.device.pupil(self.sensing.sensor.distance, self.sensing.pupil_grid, self.perturbation, progress)

    def chain(self, progress=None) -> BeaconChain:
        """A beacon through the scenario's turbulence to this sensor (:class:`BeaconChain`)."""
        if self.scenario is None:
            raise ValidationError("this system has no turbulence scenario (give one to build_system)")
        return BeaconChain.for_device(self.device, self.sensing, self.scenario, self.perturbation, progress)


def build_system(layout: str | Path | AsFabricated, sensor: str | Path | SensingRecipe,
                 turbulence: str | Path | Scenario | None = None, fabrication: dict | None = None,
                 base: str | Path | None = None, tensor_size: int | None = None) -> System:
    """The system of ``layout`` (a layout file, or a device already made) seen by ``sensor`` (a sensing
    recipe or its path) behind ``turbulence`` (a scenario or its path).  ``fabrication``: a recipe's
    ``[fabrication]`` section (the perturbation's keys, ``coupling``, ``coupling_model``, ``fab_library``;
    paths relative to ``base``); ``tensor_size``: the sensor's tensor size when the caller's differs."""
    f = dict(fabrication or {})
    base = Path(base) if base is not None else None
    fab = layout if isinstance(layout, AsFabricated) else AsFabricated.from_files(layout)
    sensing = sensor if isinstance(sensor, SensingRecipe) else load_sensing_recipe(sensor)
    if tensor_size is not None:
        sensing = replace(sensing, sensor=replace(sensing.sensor, tensor_size=tensor_size))
    scenario = turbulence if isinstance(turbulence, Scenario) or turbulence is None else load_scenario(turbulence)
    pert = Perturbation.from_config(f) if f else Perturbation()
    kind = f.get("coupling") or sensing.coupling
    cmodel = sensing.coupling_model
    if f.get("coupling_model"):
        if kind not in ("supercell", "coupling"):
            raise ValidationError('fabrication.coupling_model: needs coupling = "coupling" (or "supercell")')
        cmodel = resolve_against(base, f["coupling_model"])
    if kind != "lpa":
        fab = fab.with_coupling(kind, cmodel)
    if scenario is not None:
        check_wavelengths(fab.wavelength, scenario.wavelength, f"turbulence {turbulence}")
    if pert.has_fab_axes:
        if not f.get("fab_library"):
            raise ValidationError("fabrication.fab_library: missing; height / sidewall perturbations need a "
                                  "library with fab axes")
        lp = resolve_against(base, f["fab_library"])
        if not lp.is_file():
            raise ValidationError(f"fabrication.fab_library: {lp}: no such library")
        fab.fab_lib = load_library(lp)
    return System(fab, sensing, scenario, pert)
