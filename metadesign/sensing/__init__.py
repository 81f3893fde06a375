"""Stage 4: the as-fabricated forward model (layout -> transmission -> 8 PSFs on the sensor)."""

from .forward import CoarsePupil, coarse_pupil, full_resolution_frames, quadrant_fields, sensor_frames
from .model import AsFabricated, SensingRecipe, channel_metrics, load_sensing_recipe, render_frames
from .sensor import NoiseSpec, SensorSpec, add_noise, psf_tensor, quadrant_slices
from .transmission import Perturbation, interpolate_t, perturb_widths, pillar_transmission

__all__ = ["CoarsePupil", "coarse_pupil", "full_resolution_frames", "quadrant_fields", "sensor_frames",
           "AsFabricated", "SensingRecipe", "channel_metrics", "load_sensing_recipe", "render_frames",
           "NoiseSpec", "SensorSpec", "add_noise", "psf_tensor", "quadrant_slices",
           "Perturbation", "interpolate_t", "perturb_widths", "pillar_transmission"]
