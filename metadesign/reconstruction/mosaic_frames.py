"""Raw captures of a polarisation (mosaic) camera for ``dataset import --mosaic RECIPE`` (issue #52).

One raw capture per sample holds both polarisations: a 2 x 2 mosaic of micro-polarisers (metadesign.sensing.mosaic).
The vendor's layout is declared in a small recipe (TOML, units in the key names)::

    [raw]
    width_px = 1280          # the raw frame (a headerless .raw file needs it; images carry their own)
    height_px = 1024
    bit_depth = 12
    packing = "mono12p"      # .raw files: "mono12p" (GenICam Mono12p / Polarized12p: 2 pixels in 3 bytes,
                             # LSB first) or "uint16le" (one little-endian 16-bit word per pixel)
    msb_aligned = false      # 16-bit containers holding the value in their top bit_depth bits

    [camera]                 # the sensing recipe's [camera] keys (the physics: pattern, extinction ratio, ...)
    kind = "mosaic"
    pattern = [[90, 45], [135, 0]]
    pixel_pitch_um = 7.5
    extinction_ratio = 100.0
    unmix = true             # the frames corrected for the known extinction leak

A raw capture is a ``.raw``/``.bin`` file of that packing, or any frame ``read_frame`` reads (16-bit PNG / TIFF,
FITS, ``.npy``).  Every count must fit ``bit_depth`` bits (a wrong depth or alignment is one line); darks are
subtracted and hot pixels replaced on the raw mosaic, then :func:`demosaic_counts` gives the x and y frames at half
resolution (the camera's demosaic: 0 and 90 degree pixels, or Stokes with ``use_diagonal``, unmixed with
``unmix``), which the import treats as it treats two captured frames."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Param, Section, load_toml, parse
from ..io import atomic_path
from ..sensing.model import CAMERA_SECTION, camera_from_values
from ..sensing.mosaic import MosaicCamera, demosaic, unmix
from ..validation import ConfigError, ValidationError
from .camera_frames import fix_hot_pixels, read_frame

__all__ = [
    "RAW_SECTION",
    "RAW_SUFFIXES",
    "MosaicLayout",
    "demosaic_counts",
    "load_mosaic_layout",
    "mosaic_layout_from_dict",
    "pack_mono12p",
    "read_raw",
    "unpack_mono12p",
    "write_raw",
]

#: headerless raw files (their size and packing come from the recipe)
RAW_SUFFIXES = (".raw", ".bin")
PACKINGS = ("mono12p", "uint16le")

RAW_SECTION = Section("raw", (
    Param("width_px", int, 0, lo=0, hi=100000, help="raw frame width (0: from the image; a .raw file needs it)"),
    Param("height_px", int, 0, lo=0, hi=100000),
    Param("bit_depth", int, 12, lo=8, hi=16),
    Param("packing", str, "mono12p", choices=PACKINGS),
    Param("msb_aligned", bool, False, help="the value in the top bit_depth bits of 16-bit containers"),
))


@dataclass(frozen=True)
class MosaicLayout:
    """A vendor's raw mosaic: its size (0: from the file), bit depth, packing and the camera's physics."""

    camera: MosaicCamera
    width_px: int = 0
    height_px: int = 0
    bit_depth: int = 12
    packing: str = "mono12p"
    msb_aligned: bool = False

    def __post_init__(self):
        if self.packing == "mono12p" and self.bit_depth != 12:
            raise ConfigError("raw.packing", f"mono12p holds 12-bit pixels, but raw.bit_depth is {self.bit_depth}")
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if v % 2:
                raise ConfigError(f"raw.{name}", f"expected an even number of pixels (2 x 2 super-pixels), got {v}")
        if self.packing == "mono12p" and (self.width_px * self.height_px) % 2:
            raise ConfigError("raw.width_px", "mono12p packs pixel pairs: width x height must be even")

    @property
    def full_scale(self) -> int:
        return 2**self.bit_depth - 1

    def to_dict(self) -> dict:
        return {"width_px": self.width_px, "height_px": self.height_px, "bit_depth": self.bit_depth,
                "packing": self.packing, "msb_aligned": self.msb_aligned, "camera": self.camera.to_dict()}


def mosaic_layout_from_dict(data: dict, source: str = "recipe") -> MosaicLayout:
    cam = data.get("camera")
    if isinstance(cam, dict) and cam.get("kind", "mosaic") != "mosaic":
        raise ConfigError("camera.kind", f"a raw mosaic's camera is 'mosaic', got {cam.get('kind')!r}")
    v = parse({**data, "camera": {**(cam if isinstance(cam, dict) else {}), "kind": "mosaic"}},
              (RAW_SECTION, CAMERA_SECTION), source)
    r = v["raw"]
    return MosaicLayout(camera_from_values(v["camera"]), r["width_px"], r["height_px"], r["bit_depth"], r["packing"],
                        r["msb_aligned"])


def load_mosaic_layout(path: str | Path) -> MosaicLayout:
    return mosaic_layout_from_dict(load_toml(path), str(path))


def pack_mono12p(counts: np.ndarray) -> bytes:
    """12-bit counts -> GenICam Mono12p bytes: pixel pair (a, b) as ``a[7:0]``, ``b[3:0] a[11:8]``, ``b[11:4]``."""
    c = np.asarray(counts, np.uint16).ravel()
    a, b = c[0::2], c[1::2]
    out = np.empty((a.size, 3), np.uint8)
    out[:, 0] = a & 0xFF
    out[:, 1] = ((a >> 8) & 0x0F) | ((b & 0x0F) << 4)
    out[:, 2] = (b >> 4) & 0xFF
    return out.tobytes()


def unpack_mono12p(buf: bytes, n: int) -> np.ndarray:
    """The inverse of :func:`pack_mono12p`: ``n`` pixels (uint16)."""
    t = np.frombuffer(buf, np.uint8).reshape(-1, 3).astype(np.uint16)
    out = np.empty(2 * t.shape[0], np.uint16)
    out[0::2] = t[:, 0] | ((t[:, 1] & 0x0F) << 8)
    out[1::2] = (t[:, 1] >> 4) | (t[:, 2] << 4)
    return out[:n]


def write_raw(path: str | Path, counts: np.ndarray, layout: MosaicLayout) -> None:
    """A raw capture as the layout's camera writes it (a ``.raw`` file of its packing; MSB-aligned if so)."""
    c = np.asarray(counts, np.uint16)
    if c.max(initial=0) > layout.full_scale:
        raise ValidationError(f"{path}: counts above {layout.bit_depth} bits")
    with atomic_path(Path(path)) as tmp:
        if layout.packing == "mono12p":
            Path(tmp).write_bytes(pack_mono12p(c))
        else:
            shift = 16 - layout.bit_depth if layout.msb_aligned else 0
            Path(tmp).write_bytes((c << shift).astype("<u2").tobytes())


def read_raw(path: str | Path, layout: MosaicLayout, what: str = "raw capture") -> tuple[np.ndarray, float]:
    """A raw mosaic's counts (float64, ``(H, W)``) and the full scale of its bit depth; every count checked."""
    path = Path(path)
    if path.suffix.lower() in RAW_SUFFIXES:
        if not path.is_file():
            raise ValidationError(f"{path}: no such {what}")
        w, h = layout.width_px, layout.height_px
        if not (w and h):
            raise ValidationError(f"{path}: {what}: a headerless raw file needs raw.width_px and raw.height_px in "
                                  "the mosaic recipe")
        buf = path.read_bytes()
        n = w * h
        need = n * 3 // 2 if layout.packing == "mono12p" else 2 * n
        if len(buf) != need:
            raise ValidationError(f"{path}: {what}: {len(buf)} bytes, a {w} x {h} {layout.packing} frame has {need}")
        a = unpack_mono12p(buf, n) if layout.packing == "mono12p" else np.frombuffer(buf, "<u2")
        a = a.reshape(h, w).astype(np.int64)
        if layout.packing == "uint16le" and layout.msb_aligned:
            a = _msb(a, layout, path, what)
    else:
        f, full = read_frame(path, what)
        if full is None and np.any(f != np.round(f)):  # float data: must hold integer counts
            raise ValidationError(f"{path}: {what}: expected integer counts, got fractional values")
        a = f.astype(np.int64)
        if layout.msb_aligned:
            a = _msb(a, layout, path, what)
        if layout.width_px and a.shape != (layout.height_px, layout.width_px):
            raise ValidationError(f"{path}: {what}: {a.shape[1]} x {a.shape[0]} pixels, the mosaic recipe says "
                                  f"{layout.width_px} x {layout.height_px}")
    if a.min(initial=0) < 0 or a.max(initial=0) > layout.full_scale:
        raise ValidationError(f"{path}: {what}: counts outside [0, {layout.full_scale}] of {layout.bit_depth} bits "
                              f"(max {int(a.max())}): a wrong raw.bit_depth or raw.msb_aligned?")
    if a.shape[0] % 2 or a.shape[1] % 2:
        raise ValidationError(f"{path}: {what}: {a.shape[1]} x {a.shape[0]} pixels: not whole 2 x 2 super-pixels")
    return a.astype(np.float64), float(layout.full_scale)


def _msb(a: np.ndarray, layout: MosaicLayout, path: Path, what: str) -> np.ndarray:
    step = 2 ** (16 - layout.bit_depth)
    if np.any(a % step):
        raise ValidationError(f"{path}: {what}: raw.msb_aligned, but counts have their low {16 - layout.bit_depth} "
                              "bits set")
    return a // step


def fix_hot_mosaic(raw: np.ndarray, hot: np.ndarray) -> np.ndarray:
    """Hot pixels of a raw mosaic replaced by the median of their non-hot neighbours *behind the same
    micro-polariser* (the 3 x 3 neighbours of each 2 x 2 site's sub-image: a pixel's direct neighbours see other
    polarisations)."""
    if not hot.any():
        return raw
    out = np.array(raw, dtype=np.float64, copy=True)
    for r in range(2):
        for c in range(2):
            out[r::2, c::2] = fix_hot_pixels(out[r::2, c::2], hot[r::2, c::2])
    return out


def demosaic_counts(raw: np.ndarray, layout: MosaicLayout) -> np.ndarray:
    """``(2, H/2, W/2)`` x and y frames (counts per pixel) of a raw mosaic: the camera's demosaic, unmixed when its
    ``unmix`` is set (counts, not power per super-pixel: the import normalises the tensor)."""
    cam = layout.camera
    f = demosaic(np.asarray(raw, np.float64), cam.pattern, cam.use_diagonal)
    if cam.unmix:
        f = np.stack(unmix(f[0], f[1], cam.transmission, cam.extinction_ratio))
    return f
