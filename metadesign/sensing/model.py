"""The as-fabricated forward model behind ``metadesign psf`` and ``fab-study``:
layout file -> pillars -> (perturbed) complex t -> coarse pupils -> sensor."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..config import ConfigError, InputError, Param, Section, load_toml, parse
from ..design.phase import LensChannel, cell_coordinates, polygon_mask
from ..design.recipe import design_recipe_from_dict
from ..design.store import design_library, load_design
from ..layouts.reader import IndexRows, LayoutContents, open_layout, read_tiled_contents
from ..layouts.writer import LayoutOptions, layout_geometry, provenance_of, snap_widths
from ..library.locate import find_library
from ..library.store import UnitCellLibrary, load_library
from ..library.surrogates import CouplingNet
from ..parallel import run_tasks
from .device import Device
from .forward import CoarsePupil, block_size_for, coarse_pupil, quadrant_fields
from .mosaic import IMX250MZR_PATTERN, INCIDENT, MosaicCamera
from .sensor import NoiseSpec, SensorSpec, quadrant_slices
from .transmission import Perturbation, pillar_transmission

__all__ = ["COUPLINGS", "SensingRecipe", "load_sensing_recipe", "sensing_from_dict", "AsFabricated", "channel_metrics",
           "spot_metrics", "render_frames", "SENSING_SECTIONS", "IndexRows", "read_tiled_contents", "CAMERA_SECTION",
           "camera_from_values"]

#: the supercell models a device's pupil can take (``"coupling"``: the coupling network, ``"supercell"`` its
#: historic name, which records keep)
COUPLINGS = ("lpa", "supercell", "coupling", "peds")

#: the sensing recipe's ``[camera]``: today's two ideal frames, or a polarisation (mosaic) camera (issue #52)
CAMERA_SECTION = Section("camera", (
    Param("kind", str, "ideal", choices=("ideal", "mosaic"),
          help="ideal: the x-pol and y-pol frames as two ideal frames (today); mosaic: one raw capture of a "
               "division-of-focal-plane polarisation camera, demosaicked (metadesign.sensing.mosaic)"),
    Param("extinction_ratio", float, 0.0, lo=0, hi=1e9, help="of each micro-polariser; 0: ideal (infinite)"),
    Param("transmission", float, 1.0, lo=0, open_lo=True, hi=1, help="the pass axis's intensity transmittance"),
    Param("crosstalk_percent", float, 0.0, lo=0, hi=50, open_hi=True,
          help="% of a pixel's power leaking to its four neighbours"),
    Param("pixel_pitch_um", float, 0.0, lo=0, hi=1000,
          help="the mosaic's pixel pitch on the camera; 0: half the sensor's (the frames keep its grid)"),
    Param("pattern", list, [list(r) for r in IMX250MZR_PATTERN], rows=True, lo=0, hi=180,
          help="the 2 x 2 super-pixel, rows of angles in degrees (the IMX250MZR's: [[90, 45], [135, 0]])"),
    Param("use_diagonal", bool, False, help="demosaic through the Stokes parameters of all four pixels"),
    Param("unmix", bool, False, help="correct the known extinction leak of the 0 and 90 degree pixels"),
    Param("offsets", bool, True, help="each pixel samples its own centre (false: every pixel of a super-pixel "
                                      "its centre)"),
    Param("incident", str, "circular", choices=tuple(INCIDENT), help="the incident beam's polarisation"),
), optional=True)


def camera_from_values(c: dict) -> MosaicCamera | None:
    """The camera of a parsed ``[camera]`` section (None: today's ideal two frames)."""
    if c["kind"] == "ideal":
        return None
    er = c["extinction_ratio"]
    if 0 < er <= 1:
        raise ConfigError("camera.extinction_ratio", f"expected a number > 1, or 0 for ideal polarisers, got {er!r}")
    return MosaicCamera(c["pattern"], float("inf") if er == 0 else er, c["transmission"],
                        c["crosstalk_percent"] / 100, c["pixel_pitch_um"] or None, c["use_diagonal"], c["unmix"],
                        c["offsets"], c["incident"])


SENSING_SECTIONS = (
    Section("sensor", (
        Param("width_px", int, 640, lo=2, hi=100000),
        Param("height_px", int, 512, lo=2, hi=100000),
        Param("pixel_um", float, 15.0, lo=0, open_lo=True, hi=1000),
        Param("magnification", float, 10.0, lo=0, open_lo=True, hi=10000),
        Param("distance_mm", float, 50.0, lo=0, open_lo=True, hi=10000),
        Param("tensor_size", int, 256, lo=2, hi=4096),
    ), optional=True),
    Section("pupil", (
        Param("grid", int, 256, lo=8, hi=8192),
        Param("coupling", str, "lpa", choices=COUPLINGS,
              help="the supercell model (metadesign.library.surrogates): lpa, every pillar as in an infinite "
                   "array of itself; supercell (or coupling): plus the coupling network's terms; peds: the "
                   "certified surrogate, which a whole device cannot afford (sampled: library coupling-check "
                   "--certified)"),
        Param("coupling_model", str, None, help="the supercell model's file (default: the one fitted to the library)"),
    ), optional=True),
    Section("noise", (
        Param("gaussian_percent", float, 0.0, lo=0, hi=100),
        Param("photons_at_peak", float, 0.0, lo=0, hi=1e15),
        Param("read_noise_e", float, 0.0, lo=0),
        Param("bit_depth", int, 0, lo=0, hi=32),
        Param("seed", int, 0, lo=0),
    ), optional=True),
    CAMERA_SECTION,
)


@dataclass(frozen=True)
class SensingRecipe:
    sensor: SensorSpec
    pupil_grid: int
    noise: NoiseSpec
    coupling: str = "lpa"  # "lpa" | "supercell" (the coupling network; "coupling" in a recipe) | "peds"
    coupling_model: Path | None = None  # None: the model fitted against the device's library
    camera: MosaicCamera | None = None  # None: today's two ideal frames ([camera] kind = "ideal")


def sensing_from_dict(data: dict, source: str = "recipe") -> SensingRecipe:
    v = parse(data, SENSING_SECTIONS, source)
    s, nz = v["sensor"], v["noise"]
    for key in ("width_px", "height_px"):
        if s[key] % 4:
            raise ConfigError(f"sensor.{key}", f"must be a multiple of 4 (four quadrants of even size), got {s[key]}")
    if nz["read_noise_e"] and not nz["photons_at_peak"]:
        raise ConfigError("noise.read_noise_e", "needs noise.photons_at_peak > 0 (read noise is counted in "
                                                "photo-electrons)")
    sensor = SensorSpec(s["width_px"], s["height_px"], s["pixel_um"], s["magnification"], s["distance_mm"],
                        s["tensor_size"])
    # NoiseSpec holds the Gaussian sigma as a fraction of the peak; the recipe gives it in percent
    noise = NoiseSpec(nz["gaussian_percent"] / 100, nz["photons_at_peak"] or None, nz["read_noise_e"],
                      nz["bit_depth"] or None, nz["seed"])
    pu = v["pupil"]
    kind = "supercell" if pu["coupling"] == "coupling" else pu["coupling"]  # one spelling downstream
    if pu["coupling_model"] is not None and kind == "lpa":
        raise ConfigError("pupil.coupling_model", 'needs pupil.coupling = "supercell" (or "coupling", "peds")')
    camera = camera_from_values(v["camera"])
    if camera is not None:
        camera.frame_sensor(sensor)  # the mosaic's pitch must tile the sensor's field: one line now
    return SensingRecipe(sensor, pu["grid"], noise, kind,
                         None if pu["coupling_model"] is None else Path(pu["coupling_model"]), camera)


def load_sensing_recipe(path: str | Path) -> SensingRecipe:
    sr = sensing_from_dict(load_toml(path), str(path))
    if sr.coupling_model is not None and not sr.coupling_model.is_absolute():
        sr = replace(sr, coupling_model=Path(path).parent / sr.coupling_model)
    return sr


@dataclass
class AsFabricated:
    """A layout's pillars and the library, ready to make coarse pupils."""

    layout: LayoutContents
    lib: UnitCellLibrary
    period: float
    wavelength: float
    supercell: int
    channels: tuple[tuple[LensChannel, ...], tuple[LensChannel, ...]]

    aperture: dict | None = None  # clear-aperture record of the layout (None: the full square)
    path: Path | None = None  # the layout file
    fab_lib: UnitCellLibrary | None = None  # library with height / sidewall axes (for those perturbations)
    coupling: object | None = None  # the coupling network of the pillars (None: the LPA)
    coupling_card: dict | None = None  # its file's card
    surrogate: object | None = None  # the supercell model chosen (metadesign.library.surrogates; None: the LPA)

    def with_coupling(self, kind="supercell", model: str | Path | None = None) -> "AsFabricated":
        """This device under the supercell model ``kind``: a name of :data:`COUPLINGS` ("lpa": no coupling;
        "supercell" or "coupling": the coupling network at ``model``, default the one fitted against the
        device's library) or a supercell surrogate already made
        (:func:`metadesign.library.surrogates.surrogate`).  "peds" is refused (one line): its
        transmissions cost RCWA solves per supercell, which a whole device cannot afford; a device under
        it is estimated by sampling (``metadesign library coupling-check --certified N``)."""
        name = kind if isinstance(kind, str) else getattr(kind, "name", None)
        if name not in COUPLINGS:
            raise ConfigError("pupil.coupling", f"expected one of {', '.join(map(repr, COUPLINGS))}, got {kind!r}")
        if name == "lpa":
            return replace(self, coupling=None, coupling_card=None, surrogate=None)
        if name == "peds":
            raise ConfigError("pupil.coupling", "'peds' solves RCWA per supercell (0.1 core-s; a device has millions): "
                                                "no whole device under it; sample it with metadesign library "
                                                "coupling-check DESIGN --certified N")
        s = kind if isinstance(kind, CouplingNet) else CouplingNet(self.lib, model)
        return replace(self, coupling=s.model, coupling_card=s.file_card, surrogate=s)

    @property
    def coupling_name(self) -> str:
        return "lpa" if self.coupling is None else "supercell"

    @classmethod
    def from_files(cls, layout_path: str | Path, lib_path: str | Path | None = None) -> "AsFabricated":
        """Read a layout written by ``metadesign layout`` and find its library: ``lib_path`` if given, else
        the path recorded in the layout (relative to it), else any library with the recorded sha256."""
        layout_path = Path(layout_path)
        lc = open_layout(layout_path)
        prov = lc.provenance
        if lib_path is not None:
            path = Path(lib_path)
        else:
            recorded = prov.get("library_path")
            if recorded is None and (layout_path.parent / "design.npz").exists():  # layouts before provenance v2

                recorded = str(Path(load_design(layout_path.parent / "design.npz").meta["library"]["path"]))
            path = find_library(prov.get("library_sha256"), recorded, layout_path.parent)
        lib = load_library(path)
        if prov.get("library_sha256") and lib.identity != prov["library_sha256"]:
            raise InputError(f"{path}: library differs from the one the layout was designed with "
                             f"(sha256 {lib.identity[:12]} vs {prov['library_sha256'][:12]})")
        period = lc.period_nm * 1e-9
        if abs(period - lib.period) > 1e-12:
            raise InputError(f"layout period {lc.period_nm} nm does not match the library ({lib.period * 1e9:g} nm)")
        chans, m = channels_from_provenance(prov)
        if m != 2:
            raise InputError(f"{layout_path}: supercell {m}x{m}: the forward model needs 2x2 (one lens per quadrant)")
        return cls(lc, lib, period, lib.wavelength, m, chans, prov.get("clear_aperture"), layout_path)

    @classmethod
    def from_design(cls, design, lib_path: str | Path | None = None) -> "AsFabricated":
        """The device straight from a design (no layout file): the pillars the layout writer would place
        (widths snapped to 1 nm as it does), with the design's library.  For quick studies and the demo;
        a fab study of a real device reads its layout (:meth:`from_files`)."""
        lib = design_library(design, lib_path)
        im = design.index_map.astype(np.int32)
        if design.empty is not None:
            im[design.index_map == design.empty] = -1
        w = np.stack([snap_widths(design.atoms.wx, 1)[0], snap_widths(design.atoms.wy, 1)[0]], 1).astype(np.int64)
        p_nm, x0 = layout_geometry(design.spec.n_cells, design.spec.period)
        prov = provenance_of(design, LayoutOptions())
        lc = LayoutContents(im, w, -(w % 2), prov, int((im >= 0).sum()), 0, 0, p_nm, x0, 0.0)
        chans, m = channels_from_provenance(prov)
        return cls(lc, lib, p_nm * 1e-9, lib.wavelength, m, chans, prov.get("clear_aperture"), None)

    def aperture_mask_rows(self, r0: int, r1: int) -> np.ndarray | None:
        """Clear-aperture mask of pillar rows ``r0:r1`` (None: everything transmits)."""
        ap = self.aperture or {}
        if ap.get("kind") not in ("circle", "polygon"):
            return None

        x = cell_coordinates(self.n_cells, self.period)
        y = x[r0:r1]
        if ap["kind"] == "polygon":
            return polygon_mask(ap["wkt_m"], x, y)
        r = self.n_cells * self.period / 2
        return x[None, :] ** 2 + y[:, None] ** 2 <= r * r

    @property
    def n_cells(self) -> int:
        return self.layout.index_map.shape[0]

    @property
    def tn_scale(self) -> float:
        st = self.lib.meta["stack"]
        return float(np.sqrt(st["n_superstrate"] / st["n_substrate"]))

    def pupil_block(self, pupil_grid: int) -> int:
        """Cells per coarse-pupil block on a grid of ``pupil_grid`` samples."""
        return block_size_for(self.n_cells, pupil_grid, self.supercell)

    def pupil(self, z: float, pupil_grid: int, pert: Perturbation = Perturbation(), progress=None,
              workers: int = 1) -> CoarsePupil:
        """The coarse pupil of this device.  ``workers`` > 1 splits the block rows into contiguous shares
        on local workers (each reads its own rows: the same pupil bit for bit, test); a perturbation with
        jitter draws its pillars from one stream over the rows and always runs in one process."""
        nb = -(-self.n_cells // self.pupil_block(pupil_grid))
        if workers > 1 and not pert.jitter and nb >= 2 * workers:
            cuts = np.linspace(0, nb, workers + 1).round().astype(int)
            shares = [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:])]
            G, clamped, done, cp = None, 0, 0, None
            for (a, b), cp in run_tasks(_pupil_share, [(z, pupil_grid, pert, sh) for sh in shares], workers, self):
                if G is None:  # the whole pupil, filled share by share as they arrive
                    G = np.empty((*cp.G.shape[:2], nb, nb), np.complex64)
                G[:, :, a:b] = cp.G
                clamped += cp.n_clamped
                done += b - a
                if progress:
                    progress(done, nb)
            return CoarsePupil(G, cp.X, cp.block, cp.period, cp.wavelength, cp.z, clamped)
        return self._pupil_rows(z, pupil_grid, pert, progress)

    def _pupil_rows(self, z: float, pupil_grid: int, pert: Perturbation, progress=None,
                    block_rows: tuple[int, int] | None = None) -> CoarsePupil:
        rng = np.random.default_rng(pert.seed)  # one stream over the rows: same seed, same pillars

        def rows(r0, r1):
            t, clamped = pillar_transmission(self.layout.index_map, self.layout.atom_widths_nm, self.lib, pert,
                                             slice(r0, r1), rng, self.fab_lib, self.coupling)
            mask = self.aperture_mask_rows(r0, r1)
            if mask is not None:  # the clear aperture is a stop: opaque outside the outline
                t[~mask] = 0
            return t, clamped

        return coarse_pupil(rows, self.n_cells, self.period, self.wavelength, z, self.pupil_block(pupil_grid),
                            self.supercell, self.tn_scale, progress=progress, block_rows=block_rows)


def _pupil_share(fab: "AsFabricated", task) -> tuple[tuple[int, int], CoarsePupil]:
    """Worker: one contiguous share of a device's coarse pupil (its block rows only)."""
    z, grid, pert, share = task
    return share, fab._pupil_rows(z, grid, pert, block_rows=share)


def channels_from_provenance(prov: dict):
    """((x-pol lenses), (y-pol lenses)), supercell m: from the channel table stored in the layout (data), or
    for layouts written before it, from the embedded design recipe."""
    if prov.get("channels"):
        rows = prov["channels"]
        try:
            chans = tuple(tuple(LensChannel.from_record(r)
                                for r in sorted((r for r in rows if r["pol"] == pol), key=lambda r: r["k"]))
                          for pol in ("x", "y"))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"layout provenance: unreadable channel table ({exc})") from None
        return chans, int(prov.get("supercell", 2))

    try:
        r = design_recipe_from_dict(prov.get("recipe") or {})
    except (KeyError, TypeError, ValueError) as exc:  # ValidationError is a ValueError
        raise InputError(f"layout provenance has neither a channel table nor a readable design recipe ({exc})") \
            from None
    return (r.spec.channels_x, r.spec.channels_y), r.spec.supercell


def _best_focus(window, zs) -> tuple[float, float]:
    """(peak intensity, its distance): the maximum of ``window(z)`` (a focal window's intensity at distance
    ``z``) through focus, refined by a parabola."""
    peaks = np.array([window(z).max() for z in zs])
    i = int(np.argmax(peaks))
    if 0 < i < len(zs) - 1:  # parabolic refinement
        a, b, c_ = peaks[i - 1], peaks[i], peaks[i + 1]
        d = 0.5 * (a - c_) / (a - 2 * b + c_)
        return float(b - 0.25 * (a - c_) * d), float(zs[i] + d * (zs[1] - zs[0]))
    return float(peaks[i]), float(zs[i])


def _perfect_lens_pupil(cp: CoarsePupil, target, f: float, support: np.ndarray, q: int = 4):
    """The coarse pupil (one channel) of a perfect lens focusing on ``(target, f)`` with unit amplitude on
    ``support`` (blocks), demodulated and block-averaged (q x q samples per block) as the device's; and
    its power measure ``sum |G|^2``."""
    k0 = 2 * np.pi / cp.wavelength
    n = cp.G.shape[-1]
    xf = (cp.X[:, None] + (np.arange(q) - (q - 1) / 2) * cp.pitch / q).ravel()
    xx, yy = xf[None, :], xf[:, None]
    ph = -k0 * (np.sqrt(f * f + (xx - target[0]) ** 2 + (yy - target[1]) ** 2) - f) + k0 * (xx**2 + yy**2) / (2 * cp.z)
    g = (np.cos(ph) + 1j * np.sin(ph)).reshape(n, q, n, q).mean(axis=(1, 3)) * support
    G = g[None, None].astype(np.complex64)
    return CoarsePupil(G, cp.X, cp.block, cp.period, cp.wavelength, cp.z, 0), float(np.sum(np.abs(G) ** 2))


def channel_metrics(cp: CoarsePupil, sensor: SensorSpec, fab: AsFabricated, focus_span: float = 0.3e-3,
                    n_focus: int = 7) -> list[dict]:
    """Per channel (pol, k): focusing efficiency, Strehl at best focus, focal
    shift, centroid shift (on the sensor plane, relative to the chief ray of
    the channel's lens), crosstalk.  Channel k's light is computed from its
    own sub-lattice alone."""
    X, Y = sensor.coords()
    area_px = sensor.focal_pitch**2
    aperture = (fab.n_cells * fab.period) ** 2
    out = []
    for p in range(2):
        for k in range(1, 5):
            lens = fab.channels[p][k - 1] if fab.channels[p] else None
            ch = [k - 1]
            frame = np.zeros((sensor.height_px, sensor.width_px), np.float32)
            for q in range(1, 5):
                r, c = quadrant_slices(sensor, q)
                frame[r, c] = quadrant_fields(cp, p, X[c], Y[r], sensor.quadrant_centre(q), channels=ch) * area_px
            r, c = quadrant_slices(sensor, k)
            own = float(frame[r, c].sum())
            total = float(frame.sum())
            sub = frame[r, c]
            ys, xs = np.meshgrid(Y[r], X[c], indexing="ij")
            cx, cy = float((sub * xs).sum() / own), float((sub * ys).sum() / own)
            target = (lens.offset_x, lens.offset_y) if lens else sensor.quadrant_centre(k)
            # through focus around the designed focal length: peak intensity on a small window
            f_k = lens.focal_length if lens else cp.z
            zs = f_k + np.linspace(-focus_span, focus_span, n_focus)
            win = 6 * 1.22 * cp.wavelength * f_k / (fab.n_cells * fab.period)  # a few Airy radii
            xo = target[0] + np.linspace(-win, win, 41)
            yo = target[1] + np.linspace(-win, win, 41)
            peak, z_best = _best_focus(lambda z: quadrant_fields(cp, p, xo, yo, target, channels=ch, z=z), zs)
            # Strehl: the peak over that of a perfect lens (a converging spherical wave to the same point,
            # the same power on the same aperture), found the same way: 1 for a perfect lens, whatever the
            # Fresnel number (at low ones the best focus moves toward the lens) and the block sampling.
            ref, ref_power = _perfect_lens_pupil(cp, target, f_k, np.abs(cp.G[p, k - 1]) > 0)
            peak_ref, _ = _best_focus(lambda z: quadrant_fields(ref, 0, xo, yo, target, channels=[0], z=z), zs)
            power = float(np.sum(np.abs(cp.G[p, k - 1]) ** 2))
            strehl = peak / (peak_ref * power / ref_power) if peak_ref > 0 and ref_power > 0 else 0.0
            out.append({
                "pol": "xy"[p], "k": k, "quadrant": ["QI", "QII", "QIII", "QIV"][k - 1],
                "design_focal_length_mm": f_k * 1e3,
                "focusing_efficiency": own / aperture,
                "strehl": strehl,
                "focal_shift_mm": (z_best - f_k) * 1e3,
                # relative to the chief ray through the aperture centre: a channel focusing at f_k
                # lands at offset * z / f_k on the sensor plane z
                "centroid_shift_um": [1e6 * (cx - target[0] * cp.z / f_k), 1e6 * (cy - target[1] * cp.z / f_k)],
                "crosstalk": 1 - own / total if total > 0 else 0.0,
            })
    return out


def spot_metrics(cp: CoarsePupil, sensor: SensorSpec, fab: AsFabricated, focus_span: float = 0.3e-3,
                 n_focus: int = 7, airy_radii: float = 2.0, intensity=None) -> list[dict]:
    """Per channel (pol, k), measured on the total field, as a camera sees it (every sub-lattice at once):
    ``spot_efficiency`` the power within ``airy_radii`` Airy radii (1.22 lambda f_k / D) of the channel's
    spot over the incident power; ``spot_strehl`` the spot's peak at best focus over that of a perfect lens
    to the same spot delivering the same power into the quadrant; ``stray`` the fraction of the quadrant's
    power outside the spot; ``focal_shift_mm`` of the total field's peak.  Unlike :func:`channel_metrics`
    (one sub-lattice's light) these need no attribution of light to pillars, so they hold under the
    supercell coupling model, where a pillar's light is not its own.

    ``intensity(pol, xo, yo, centre, z=None)``: the device's focal intensity (default
    :func:`~metadesign.sensing.forward.quadrant_fields` of ``cp``; e.g. a sampled estimate,
    :class:`~metadesign.sensing.sampled.SampledIntensity`); ``cp`` still gives the grid and the support."""
    if intensity is None:
        def intensity(pol, xo, yo, centre, z=None):
            return quadrant_fields(cp, pol, xo, yo, centre, z=z)
    X, Y = sensor.coords()
    area_px = sensor.focal_pitch**2
    D = fab.n_cells * fab.period
    aperture = D * D
    out = []
    for p in range(2):
        frame = np.zeros((sensor.height_px, sensor.width_px), np.float32)
        for q in range(1, 5):
            r, c = quadrant_slices(sensor, q)
            frame[r, c] = intensity(p, X[c], Y[r], sensor.quadrant_centre(q)) * area_px
        for k in range(1, 5):
            lens = fab.channels[p][k - 1] if fab.channels[p] else None
            target = (lens.offset_x, lens.offset_y) if lens else sensor.quadrant_centre(k)
            f_k = lens.focal_length if lens else cp.z
            r, c = quadrant_slices(sensor, k)
            sub = frame[r, c]
            ys, xs = np.meshgrid(Y[r], X[c], indexing="ij")
            t_plane = (target[0] * cp.z / f_k, target[1] * cp.z / f_k)
            rad = airy_radii * 1.22 * cp.wavelength * cp.z / D
            inside = (xs - t_plane[0]) ** 2 + (ys - t_plane[1]) ** 2 <= rad * rad
            spot, quad = float(sub[inside].sum()), float(sub.sum())
            zs = f_k + np.linspace(-focus_span, focus_span, n_focus)
            win = 6 * 1.22 * cp.wavelength * f_k / D
            xo = target[0] + np.linspace(-win, win, 41)
            yo = target[1] + np.linspace(-win, win, 41)
            peak, z_best = _best_focus(lambda z: intensity(p, xo, yo, target, z=z), zs)
            # the reference: a perfect lens to the same spot whose quadrant receives the same power
            ref, _ = _perfect_lens_pupil(cp, target, f_k, np.abs(cp.G[p].sum(0)) > 0)
            peak_ref, _ = _best_focus(lambda z: quadrant_fields(ref, 0, xo, yo, target, channels=[0], z=z), zs)
            ref_quad = float(quadrant_fields(ref, 0, X[c], Y[r], sensor.quadrant_centre(k)).sum()) * area_px
            strehl = peak / (peak_ref * quad / ref_quad) if peak_ref > 0 and ref_quad > 0 and quad > 0 else 0.0
            out.append({"pol": "xy"[p], "k": k, "spot_efficiency": spot / aperture, "spot_strehl": strehl,
                        "stray": 1 - spot / quad if quad > 0 else 0.0, "focal_shift_mm": (z_best - f_k) * 1e3})
    return out


def render_frames(fab: AsFabricated, sr: SensingRecipe, pert: Perturbation = Perturbation(),
                  e_in: np.ndarray | None = None, progress=None) -> tuple[np.ndarray, CoarsePupil]:
    cp = fab.pupil(sr.sensor.distance, sr.pupil_grid, pert, progress)
    return Device(cp, sr.sensor).frames(e_in), cp
