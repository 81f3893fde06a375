"""One turbulent beacon sample through to the sensor: screens -> split step ->
collimated receiver field -> beam reducer -> as-fabricated metasurface ->
8 PSFs.  The demo, ``metadesign dataset`` and the tests all call
:class:`BeaconChain` (one code path)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from ..sensing.device import check_wavelengths
from ..sensing.device import Device
from ..sensing.forward import CoarsePupil
from ..sensing.model import AsFabricated, SensingRecipe
from ..sensing.transmission import Perturbation
from .path import Scenario
from .propagate import Turbulence

__all__ = ["BeaconChain", "BeaconSample"]


@dataclass
class BeaconSample:
    seed: int  # the screens' seed: Turbulence.screens(seed) regenerates them bit for bit
    rytov: float  # nominal Rytov number of the path
    received: np.ndarray  # (n, n) complex64: collimated field on the turbulence grid, 0 outside the receiver
    e_in: np.ndarray  # (N, N) complex64: that field imaged onto the metasurface's coarse pupil grid
    frames: np.ndarray | None  # (2, H, W) float32 sensor frames (noise-free; None: not rendered)
    tensor: np.ndarray | None  # (8, S, S) float32 PSF tensor (noise-free; None: not rendered)
    timings: dict


class BeaconChain:
    """A device's coarse pupil, a sensor and a turbulence scenario, ready to draw samples.

    The coarse pupil (the costly part: every pillar of the layout) is built once,
    by :meth:`for_device`, and is all a worker needs; a sample then costs one
    turbulence draw plus eight matrix Fourier transforms."""

    def __init__(self, pupil: CoarsePupil, sensing: SensingRecipe, scenario: Scenario, aperture: float):
        check_wavelengths(pupil.wavelength, scenario.wavelength, "turbulence scenario")  # one wavelength per chain
        self.pupil, self.sensing = pupil, sensing
        # the forward-model contract: one render per sample (through the recipe's camera, if it names one)
        self.device = Device(pupil, sensing.sensor, camera=sensing.camera)
        self.turbulence = Turbulence(replace(scenario, metasurface_aperture=aperture))

    @classmethod
    def for_device(cls, fab: AsFabricated, sensing: SensingRecipe, scenario: Scenario,
                   pert: Perturbation = Perturbation(), progress=None) -> "BeaconChain":
        chain = cls(fab.pupil(sensing.sensor.distance, sensing.pupil_grid, pert, progress), sensing, scenario,
                    fab.n_cells * fab.period)
        chain.fab = fab
        return chain

    def at(self, rytov: float) -> Turbulence:
        return self.turbulence.at_rytov(rytov)

    def sample(self, seed: int, rytov: float, render: bool = True) -> BeaconSample:
        """Beacon ``seed`` at ``rytov`` through to the sensor (``render=False``: up to the received field, for
        a caller that changes the field before rendering it)."""
        tb = self.at(rytov)
        t0 = time.perf_counter()
        ph = tb.screens(seed)
        t1 = time.perf_counter()
        field = tb.element.forward(tb.source, ph)
        t2 = time.perf_counter()
        received = tb.collimated(field)
        e_in = tb.to_metasurface(field, self.pupil.G.shape[-1])
        t3 = time.perf_counter()
        shot = self.device.render(e_in) if render else None
        t4 = time.perf_counter()
        return BeaconSample(seed, rytov, received, e_in, None if shot is None else shot.frames,
                            None if shot is None else shot.psfs,
                            {"screens": t1 - t0, "split_step": t2 - t1, "to_metasurface": t3 - t2, "psf": t4 - t3})
