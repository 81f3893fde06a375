"""The orientation check of captured frames (issue #52), as the capture import and the evaluation use it: the
mean flat capture against the reference device's calibration signature
(:mod:`metadesign.sensing.orientation`), refused in one line when it is turned otherwise than declared, put
back when it is declared; and the check's record, without which captures are not evaluated."""

from __future__ import annotations

import numpy as np

from ..sensing.orientation import (
    ORIENTATIONS,
    correct_frames,
    diagnose,
    orient_frames,
    signature_record,
)
from ..validation import ValidationError

__all__ = ["captured_shape", "check_flat", "check_orientation_name", "check_orientation_record", "put_back", "turned_hint"]


def check_orientation_name(name: str) -> str:
    if name not in ORIENTATIONS:
        raise ValidationError(f"--orientation: expected one of {', '.join(ORIENTATIONS)}, got {name!r}")
    return name


def captured_shape(shape: tuple[int, int], orientation: str) -> tuple[int, int]:
    """(rows, cols) of a camera frame that arrives in ``orientation`` for a sensor of ``shape``."""
    return tuple(orient_frames(np.zeros((2, *shape), bool), check_orientation_name(orientation)).shape[-2:])


def turned_hint(got, shape) -> str:
    """The hint a frame of the sensor's shape crossed gets (a camera mounted on its side)."""
    return (" (a camera turned by 90 degrees? pass --orientation transpose, rot90 or rot270)"
            if tuple(got) == tuple(shape)[::-1] and got[0] != got[1] else "")


def put_back(frames, orientation: str) -> list[np.ndarray]:
    """A sample's two frames ``[x, y]`` as they arrived in ``orientation``, in the contract's orientation."""
    if orientation == "identity":
        return list(frames)
    return list(correct_frames(np.stack(frames), orientation))


def check_flat(flat: np.ndarray, reference_frames: np.ndarray, declared: str, where) -> tuple[np.ndarray, object]:
    """The mean flat capture ``(2, H, W)`` (as the camera gave it) checked against the reference device's
    nominal flat frames: refused in one line (``where: ...``) unless it is in the ``declared`` orientation
    (as far as the device's signature tells); returns it put back in the contract's orientation, and the
    :class:`~metadesign.sensing.orientation.Verdict`."""
    check_orientation_name(declared)
    verdict = diagnose(flat, signature_record(reference_frames), declared)
    if verdict.problem() is not None:
        raise ValidationError(f"{where}: {verdict.problem()}")
    return correct_frames(flat, declared), verdict


def check_orientation_record(attrs: dict, where) -> None:
    """Refuse captures (a dataset with ``propagation = "slm"``) whose flat frames were not checked for their
    orientation at import, in one line; synthetic datasets pass."""
    if attrs.get("propagation") != "slm":
        return
    rec = (attrs.get("provenance") or {}).get("orientation")
    if not isinstance(rec, dict) or rec.get("problem"):
        raise ValidationError(f"{where}: captures imported without the orientation check of their flat frames "
                              "(an import before issue #52): import them again")
