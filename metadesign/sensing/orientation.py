"""Which way round a camera frame is (issue #52): the flat-wavefront calibration signature of a device.

A flat wavefront through the sensor puts eight spots on the two polarisation frames, one per quadrant
window, each with its own defocus (the diversity ladder: Table S1's focal lengths around the sensor
distance), so their sizes and shapes differ channel by channel.  That ladder is a signature: a frame
flipped up-down (a relay that inverts one axis), mirrored left-right, rotated by 180 degrees (a single
relay inverts the image), transposed or rotated by 90 degrees (a square camera mounted on its side), or
the two polarisation frames swapped, permutes it.  A shifted or rescaled frame (camera offset, relay
magnification) moves the spots and scales them, which the same features measure.

Kernel (pure functions on arrays; the stand-alone example ``examples/deploy_onnx.py`` carries a numpy copy
that a test holds to this one):

* :func:`signature` -- per channel (tensor order: x-pol QI..QIV, y-pol QI..QIV), from each quadrant window
  smoothed by a box of ``smooth`` pixels and clipped at ``threshold`` of its peak: the spot's centroid
  offset from the window centre (px), its size (the root of the second moment's trace, px) and its
  ellipticity ``e1 = (mxx - myy) / (mxx + myy)``, ``e2 = 2 mxy / (mxx + myy)``.
* :func:`diagnose` -- every candidate orientation (:data:`ORIENTATIONS`: the flips and rotations a frame's
  shape allows, each with or without swapping the polarisation frames) undone on the frames, its signature
  compared with the expected one (the rms difference of the log sizes about their mean, and of the
  ellipticities), the best match taken; then the similarity (shift, scale) that maps the expected centres
  onto the measured ones.  A :class:`Verdict` says what was found; :meth:`Verdict.problem` is the one line
  that refuses a frame (wrong orientation, poor match, ambiguity).

Conventions: a frame is ``array[row, col]`` as the camera's contract defines it
(:mod:`metadesign.sensing.sensor`); an orientation names what happened to the nominal frame on its way to
the file (``flip-ud``: rows reversed), so correcting a frame applies the inverse
(:func:`correct_frames`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["CHI2_MAX", "DESCRIPTIONS", "FLOOR", "ORIENTATIONS", "SCALE_TOL", "SHIFT_TOL_PX", "SIGNATURE_FORMAT",
           "Verdict", "chi2", "correct_frames", "default_parameters", "diagnose", "expected_of", "frame_noise",
           "orient_frames", "orientations_for", "relative", "signature", "signature_record"]

SIGNATURE_FORMAT = "metadesign.flat-signature/1"

#: the geometric part of an orientation: what it does to a nominal frame (rows, columns)
_GEOMETRY = {
    "identity": lambda f: f,
    "flip-ud": lambda f: f[..., ::-1, :],
    "flip-lr": lambda f: f[..., :, ::-1],
    "rot180": lambda f: f[..., ::-1, ::-1],
    "transpose": lambda f: np.swapaxes(f, -1, -2),
    "rot90": lambda f: np.rot90(f, 1, axes=(-2, -1)),
    "rot270": lambda f: np.rot90(f, -1, axes=(-2, -1)),
    "anti-transpose": lambda f: np.rot90(np.swapaxes(f, -1, -2), 2, axes=(-2, -1)),
}
_INVERSE = {"rot90": "rot270", "rot270": "rot90"}
_WORDS = {
    "identity": "as the contract says",
    "flip-ud": "flipped up-down (a relay that inverts the rows?)",
    "flip-lr": "mirrored left-right (a relay that inverts the columns?)",
    "rot180": "rotated by 180 degrees (a single relay inverts the image?)",
    "transpose": "transposed (rows and columns exchanged)",
    "rot90": "rotated by 90 degrees (counter-clockwise)",
    "rot270": "rotated by 90 degrees (clockwise)",
    "anti-transpose": "transposed about the anti-diagonal",
}

#: every orientation a frame may arrive in: a geometric one, optionally with the polarisation frames swapped
ORIENTATIONS = tuple(list(_GEOMETRY) + [f"swap-pol+{g}" if g != "identity" else "swap-pol" for g in _GEOMETRY])


def _split(name: str) -> tuple[bool, str]:
    if name not in ORIENTATIONS:
        raise ValueError(f"orientation: expected one of {', '.join(ORIENTATIONS)}, got {name!r}")
    swap = name.startswith("swap-pol")
    geo = name[len("swap-pol+"):] if "+" in name else ("identity" if swap else name)
    return swap, geo


#: one phrase per orientation, for the one-line errors
DESCRIPTIONS = {}
for _n in ORIENTATIONS:
    _s, _g = _split(_n)
    DESCRIPTIONS[_n] = ("its two polarisation frames are swapped" + ("" if _g == "identity" else
                                                                     " and it is " + _WORDS[_g])) \
        if _s else ("it is " + _WORDS[_g])

#: the thresholds of :meth:`Verdict.problem` (measured: benchmarks/bench_orientation.py,
#: sensing/orientation-check.json): the largest reduced chi-square of a match (exactly one orientation must
#: match), and the alignment a frame may show before it is off
CHI2_MAX = 6.0
SHIFT_TOL_PX = 1.0
SCALE_TOL = 0.01
#: the log ensquared energy a frame may differ by without noise (the relay's magnification, the device as
#: made against its model)
FLOOR = 0.05


def orientations_for(shape: tuple[int, int], expected: tuple[int, int] | None = None) -> tuple[str, ...]:
    """The orientations whose undoing turns a frame of ``shape`` (rows, cols) into one of ``expected`` (default
    ``shape``): all of them for a square frame; for another, the flips and the 180-degree rotation (with or
    without the swap) when the shapes agree, the transposes and 90-degree rotations when they are crossed."""
    expected = tuple(shape) if expected is None else tuple(expected)
    out = []
    for n in ORIENTATIONS:
        g = _split(n)[1]
        turned = g in ("transpose", "rot90", "rot270", "anti-transpose")
        if (tuple(shape[::-1]) if turned else tuple(shape)) == expected:
            out.append(n)
    return tuple(out)


def orient_frames(frames: np.ndarray, name: str) -> np.ndarray:
    """The nominal frames ``(2, H, W)`` as they arrive in orientation ``name``."""
    swap, geo = _split(name)
    f = _GEOMETRY[geo](np.asarray(frames))
    return np.ascontiguousarray(f[::-1] if swap else f)


def correct_frames(frames: np.ndarray, name: str) -> np.ndarray:
    """Frames that arrived in orientation ``name`` put back as the contract defines them (the inverse of
    :func:`orient_frames`)."""
    swap, geo = _split(name)
    f = np.asarray(frames)
    f = f[::-1] if swap else f
    return np.ascontiguousarray(_GEOMETRY[_INVERSE.get(geo, geo)](f))


_LABELS = np.arange(18).reshape(2, 3, 3)


def relative(declared: str, candidate: str) -> str:
    """The orientation in which frames that arrived in ``declared`` are left after correcting them as if they
    had arrived in ``candidate``."""
    g = correct_frames(orient_frames(_LABELS, declared), candidate)
    return next(n for n in ORIENTATIONS if np.array_equal(orient_frames(_LABELS, n), g))


def _windows(shape: tuple[int, int]):
    """(row slice, col slice) of the four quadrant windows (reading order) of a frame of ``shape``."""
    h2, w2 = shape[0] // 2, shape[1] // 2
    for k in range(4):
        yield (slice(0, h2) if k < 2 else slice(h2, shape[0])), (slice(0, w2) if k % 2 == 0 else slice(w2, shape[1]))


def _integral(a: np.ndarray) -> np.ndarray:
    c = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    c[1:, 1:] = a.cumsum(0).cumsum(1)
    return c


def _box_sums(c: np.ndarray, n: int) -> np.ndarray:
    """The sums over every ``n x n`` square of the image whose integral image is ``c``."""
    n = int(min(n, c.shape[0] - 1, c.shape[1] - 1))
    return c[n:, n:] - c[:-n, n:] - c[n:, :-n] + c[:-n, :-n]


def default_parameters(shape: tuple[int, int]) -> dict:
    """The signature's parameters for a frame of ``shape``: the smoothing square of the centroids (px, odd,
    1/64 of the short side), their clip level, and the ensquared-energy squares (1/64, 1/32, 1/16, 1/8 of the
    short side, odd)."""
    m = min(shape)
    return {"smooth_px": int(max(1, m // 64) | 1), "threshold": 0.25,
            "boxes_px": [int(max(1, m // d) | 1) for d in (64, 32, 16, 8)]}


def frame_noise(frame: np.ndarray) -> float:
    """The pixel noise of a frame (its sigma): 1.4826 x the median absolute difference of neighbouring
    pixels along the rows, / sqrt 2 (a spot's smooth light hardly changes from one pixel to the next); their
    rms / sqrt 2 where that median is 0 (a frame of few counts)."""
    d = np.diff(np.asarray(frame, np.float64), axis=-1)
    mad = np.median(np.abs(d - np.median(d)))
    return float((1.4826 * mad if mad > 0 else np.sqrt(np.mean(d**2))) / np.sqrt(2))


def signature(frames: np.ndarray, params: dict | None = None) -> np.ndarray:
    """``(8, 3 + 2 B)`` float64 per channel (x-pol QI..QIV, y-pol QI..QIV) of flat ``frames`` ``(2, H, W)``:
    the spot's centroid offset from its window's centre ``(dx, dy)`` (px, columns and rows) and size (px),
    the log of the largest power in a square of each of the ``B`` sides ``boxes_px`` (ensquared energy), and
    that log's standard error from the frame's pixel noise (:func:`frame_noise`).  Each window's median is
    its background; the centroid and size are the moments of the window smoothed over ``smooth_px``,
    clipped at ``threshold`` x its peak, then again within 2.5 sizes of that centre."""
    f = np.asarray(frames, np.float64)
    if f.ndim != 3 or f.shape[0] != 2:
        raise ValueError(f"signature: expected frames of shape (2, H, W), got {f.shape}")
    prm = params or default_parameters(f.shape[-2:])
    b, thr, boxes = int(prm["smooth_px"]), float(prm["threshold"]), [int(n) for n in prm["boxes_px"]]
    out = np.zeros((8, 3 + 2 * len(boxes)))
    for p in range(2):
        sigma = frame_noise(f[p])
        for k, (r, c) in enumerate(_windows(f.shape[-2:])):
            win = f[p][r, c] - np.median(f[p][r, c])
            ii = _integral(win)
            ee = np.array([max(_box_sums(ii, n).max(), 1e-300) for n in boxes])
            out[4 * p + k, 3:] = np.r_[np.log(ee), sigma * np.asarray(boxes) / ee]
            q = _box_sums(_integral(np.pad(win, b // 2)), b) / (b * b)
            w = np.clip(q - thr * q.max(), 0.0, None)
            yy, xx = np.indices(w.shape, dtype=np.float64)
            m = _moments(w, yy, xx)
            if m is None:
                continue
            for _ in range(2):
                rad = 2.5 * np.sqrt(m[2] + m[3]) + 2.0
                m = _moments(np.where((xx - m[0]) ** 2 + (yy - m[1]) ** 2 <= rad * rad, w, 0.0), yy, xx) or m
            out[4 * p + k, :3] = (m[0] - (w.shape[1] - 1) / 2, m[1] - (w.shape[0] - 1) / 2, np.sqrt(m[2] + m[3]))
    return out


def _moments(w: np.ndarray, yy: np.ndarray, xx: np.ndarray):
    s = w.sum()
    if not s > 0:
        return None
    cx, cy = (w * xx).sum() / s, (w * yy).sum() / s
    return cx, cy, (w * (xx - cx) ** 2).sum() / s, (w * (yy - cy) ** 2).sum() / s


def chi2(sig: np.ndarray, ref: np.ndarray, floor: float = FLOOR) -> float:
    """Reduced chi-square of a signature against the expected one: the log ensquared energies' differences,
    each channel's mean difference removed (a channel's efficiency and the exposure are not its shape), over
    their standard errors and ``floor`` in quadrature."""
    nb = (sig.shape[1] - 3) // 2
    d = sig[:, 3:3 + nb] - ref[:, 3:3 + nb]
    var = sig[:, 3 + nb:] ** 2 + ref[:, 3 + nb:] ** 2 + floor**2
    w = 1.0 / var
    d = d - (w * d).sum(axis=1, keepdims=True) / w.sum(axis=1, keepdims=True)
    return float((d**2 * w).sum() / (d.shape[0] * (nb - 1)))


def _similarity(ref: np.ndarray, meas: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray, float]:
    """Weighted least-squares ``meas = scale * ref + shift`` (points (N, 2) about the frame centre, weights
    (N,)): (scale, shift, weighted rms residual px)."""
    w = w / w.sum()
    rm, mm = (w[:, None] * ref).sum(0), (w[:, None] * meas).sum(0)
    a, b = ref - rm, meas - mm
    s = float((w[:, None] * a * b).sum() / (w[:, None] * a * a).sum())
    t = mm - s * rm
    res = meas - (s * ref + t)
    return s, t, float(np.sqrt((w * (res**2).sum(axis=1)).sum()))


def _centres(sig: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(8, 2) spot centres about the frame centre (px, columns and rows) from a signature."""
    out = np.empty((8, 2))
    for p in range(2):
        for k, (r, c) in enumerate(_windows(shape)):
            out[4 * p + k] = (sig[4 * p + k, 0] + (c.start + c.stop - 1) / 2 - (shape[1] - 1) / 2,
                              sig[4 * p + k, 1] + (r.start + r.stop - 1) / 2 - (shape[0] - 1) / 2)
    return out


@dataclass(frozen=True)
class Verdict:
    """What :func:`diagnose` found: the orientation the frames arrived in (``best``), its reduced chi-square
    against the expected signature and the runner-up's, every orientation that matches (chi-square <=
    :data:`CHI2_MAX`), the orientations the device's own signature cannot tell from the contract's
    (``symmetric``), the declared orientation, and the shift (px, columns and rows) and scale of the spots
    against the expected ones once the best orientation is undone."""

    best: str
    chi2: float
    runner_up: str
    runner_up_chi2: float
    matching: tuple[str, ...]
    symmetric: tuple[str, ...]
    shift_px: tuple[float, float]
    scale: float
    residual_px: float
    declared: str = "identity"

    def _consistent(self, a: str) -> bool:
        """Every matching orientation is ``a`` up to the device's symmetry."""
        return all(m == a or relative(a, m) in self.symmetric for m in self.matching)

    @property
    def accepted(self) -> bool:
        return self.problem() is None

    @property
    def aligned(self) -> bool:
        """Shift within :data:`SHIFT_TOL_PX` and scale within :data:`SCALE_TOL` of the contract's."""
        return bool(np.hypot(*self.shift_px) <= SHIFT_TOL_PX and abs(self.scale - 1) <= SCALE_TOL)

    def problem(self, flag: str = "--orientation") -> str | None:
        """The one line that refuses the frames (None: they are in the declared orientation, as far as the
        device's signature tells; the alignment is the caller's to correct or to refuse)."""
        if not self.matching:
            return (f"the flat frame does not match the device's calibration signature in any orientation "
                    f"(closest {self.best}, chi2 {self.chi2:.3g} > {CHI2_MAX:g}): another device, sensor or relay, "
                    "or not a flat-wavefront frame")
        if self.declared in self.matching and self._consistent(self.declared):
            return None
        if not self._consistent(self.best):
            return (f"the flat frame's orientation is ambiguous ({self.best} chi2 {self.chi2:.3g}, {self.runner_up} "
                    f"{self.runner_up_chi2:.3g}, both <= {CHI2_MAX:g}): average more flat frames")
        if self.declared == "identity":
            return f"frame orientation: {DESCRIPTIONS[self.best]}: pass {flag} {self.best}"
        return (f"frame orientation: declared {self.declared}, but {DESCRIPTIONS[self.best]} "
                f"(pass {flag} {self.best})")

    def note(self) -> str | None:
        """A warning when the device's signature cannot tell some orientations apart (a design without a
        defocus ladder): the check does not protect against those."""
        if not self.symmetric:
            return None
        return ("the device's calibration signature is the same " + ", ".join(self.symmetric) +
                ": the flat frame cannot tell those orientations apart (a design without a defocus ladder)")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["shift_px"] = [round(float(v), 3) for v in self.shift_px]
        for k in ("chi2", "runner_up_chi2", "scale", "residual_px"):
            d[k] = round(float(d[k]), 5) if np.isfinite(d[k]) else None
        d["matching"], d["symmetric"] = list(self.matching), list(self.symmetric)
        d["aligned"], d["problem"] = self.aligned, self.problem()
        return d


def signature_record(frames: np.ndarray, params: dict | None = None) -> dict:
    """The expected signature of a device's nominal flat frames as a JSON-able record (the deployment
    contract's ``calibration_signature``): the parameters, the thresholds, per channel the features of
    :func:`signature` (without their errors: a model's frames have no noise), and the orientations the
    signature itself cannot tell from the contract's (``symmetric``)."""
    f = np.asarray(frames, np.float64)
    prm = params or default_parameters(f.shape[-2:])
    sig = signature(f, prm)
    nb = len(prm["boxes_px"])
    rec = {"format": SIGNATURE_FORMAT, "frame_px": {"height": int(f.shape[-2]), "width": int(f.shape[-1])},
           **prm, "features": ["dx_px", "dy_px", "size_px"] + [f"log_ee_{n}" for n in prm["boxes_px"]],
           "channels": [[round(float(v), 4) for v in row[:3 + nb]] for row in sig],
           "chi2_max": CHI2_MAX, "floor": FLOOR, "shift_tol_px": SHIFT_TOL_PX, "scale_tol": SCALE_TOL,
           "meaning": "per channel (x-pol QI..QIV, y-pol QI..QIV) of a flat-wavefront frame, each quadrant window "
                      "less its median: the spot's centroid offset from the window centre (dx, dy: columns, rows) "
                      "and size sqrt(mxx + myy) of the window box-smoothed over smooth_px and clipped at threshold "
                      "x its peak (then within 2.5 sizes of that centre); log_ee_N: the log of the largest power "
                      "in an N x N square.  A capture's orientation is the flip / rotation / polarisation swap "
                      "whose undoing matches: reduced chi-square of the log_ee differences (each channel's mean "
                      "difference removed; errors: the frame's pixel noise sigma x N / ee, floor in quadrature) "
                      "<= chi2_max; refused unless the matches are one orientation up to the device's own "
                      "symmetry (symmetric: the orientations its nominal signature cannot tell from the "
                      "contract's); then the shift and scale of the centroids (weights 1 / size^4)"}
    exp = expected_of(rec)[0]
    rec["symmetric"] = [n for n in orientations_for(f.shape[-2:])[1:]
                        if chi2(signature(orient_frames(f, n), prm), exp) <= CHI2_MAX]
    return rec


def expected_of(record: dict) -> tuple[np.ndarray, dict, tuple[int, int]]:
    """(signature (8, 3 + 2 B) with zero errors, parameters, frame shape (rows, cols)) of a
    :func:`signature_record`."""
    ch = np.asarray(record["channels"], np.float64)
    prm = {k: record[k] for k in ("smooth_px", "threshold", "boxes_px")}
    return (np.concatenate([ch, np.zeros((8, len(prm["boxes_px"])))], axis=1), prm,
            (int(record["frame_px"]["height"]), int(record["frame_px"]["width"])))


def diagnose(frames: np.ndarray, record: dict, declared: str = "identity") -> Verdict:
    """Which orientation (:data:`ORIENTATIONS`) the flat ``frames`` ``(2, H, W)`` arrived in, against the
    device's expected signature ``record`` (:func:`signature_record`), and the spots' shift and scale once it
    is undone; ``declared``: the orientation the user says the frames are in.  Frames whose shape no
    orientation turns into the record's raise ValueError."""
    _split(declared)
    expected, prm, shape = expected_of(record)
    f = np.asarray(frames, np.float64)
    names = orientations_for(f.shape[-2:], shape)
    if not names:
        raise ValueError(f"frame of {f.shape[-1]} x {f.shape[-2]} pixels: the camera has {shape[1]} x {shape[0]}")
    scores = []
    for name in names:
        sig = signature(correct_frames(f, name), prm)
        scores.append((chi2(sig, expected), name, sig))
    scores.sort(key=lambda s: s[0])
    (c0, best, sig), (c1, second, _) = scores[0], scores[1]
    # a centroid's scatter grows as the square of its spot's size (its power spread over more noisy pixels)
    s, t, res = _similarity(_centres(expected, shape), _centres(sig, shape),
                            1.0 / np.maximum(expected[:, 2], 1.0) ** 4)
    return Verdict(best, c0, second, c1, tuple(n for c, n, _ in scores if c <= CHI2_MAX),
                   tuple(record.get("symmetric", ())), (float(t[0]), float(t[1])), s, res, declared)
