"""Stage 4: the as-fabricated forward model (layout -> transmission -> 8 PSFs on the sensor), the typed
:class:`~.device.Device` the estimators take, the differentiable twin (:mod:`.twin`), the camera and
relay models of captures (:mod:`.camera`), phase maps and the fab study; a device under a costly model
by sampling its supercells (:mod:`.sampled`)."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562)
_EXPORTS = {
    "Alignment": "camera", "CameraSpec": "camera", "Device": "device", "ReceiverCrop": "device",
    "CoarsePupil": "forward", "coarse_pupil": "forward", "full_resolution_frames": "forward",
    "quadrant_fields": "forward", "sensor_frames": "forward", "AsFabricated": "model", "SensingRecipe": "model",
    "channel_metrics": "model", "load_sensing_recipe": "model", "render_frames": "model", "fab_study": "render",
    "render_psf": "render", "save_psf": "render", "NoiseSpec": "detector", "SensorSpec": "sensor",
    "add_noise": "detector", "Detector": "detector", "psf_tensor": "sensor", "quadrant_slices": "sensor", "Perturbation": "transmission",
    "interpolate_t": "transmission", "perturb_widths": "transmission", "pillar_transmission": "transmission",
    "spot_metrics": "model", "quadrant_transform": "forward", "SampledIntensity": "sampled",
    "delta_pupil": "sampled", "eligible_supercells": "sampled", "sampled_spot_metrics": "sampled",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
