"""Stage 4: the as-fabricated forward model (layout -> transmission -> 8 PSFs on the sensor), the typed
:class:`~.device.Device` the estimators take, the differentiable twin (:mod:`.twin`), the camera and
relay models of captures (:mod:`.camera`), phase maps and the fab study."""

from .camera import Alignment, CameraSpec
from .device import Device, ReceiverCrop
from .forward import CoarsePupil, coarse_pupil, full_resolution_frames, quadrant_fields, sensor_frames
from .model import AsFabricated, SensingRecipe, channel_metrics, load_sensing_recipe, render_frames
from .render import fab_study, render_psf, save_psf
from .sensor import NoiseSpec, SensorSpec, add_noise, psf_tensor, quadrant_slices
from .transmission import Perturbation, interpolate_t, perturb_widths, pillar_transmission

__all__ = ["Alignment", "CameraSpec", "Device", "ReceiverCrop", "fab_study", "render_psf", "save_psf",
           "CoarsePupil", "coarse_pupil", "full_resolution_frames", "quadrant_fields", "sensor_frames",
           "AsFabricated", "SensingRecipe", "channel_metrics", "load_sensing_recipe", "render_frames",
           "NoiseSpec", "SensorSpec", "add_noise", "psf_tensor", "quadrant_slices",
           "Perturbation", "interpolate_t", "perturb_widths", "pillar_transmission"]
