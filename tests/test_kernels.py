"""Issue #35: the compiled kernels against their numpy twins, bit for bit (the discretizer's index map and
error sums, the OASIS placements), and their building blocks against numpy itself (the wrap, the pairwise
sum).  Without numba the twins are the path and these tests are skipped."""

import dataclasses
import math

import numpy as np
import pytest

from metadesign import jit
from metadesign.design import Metric, NearestAtom, SupercellSpec, paper_channels
from metadesign.design.build import map_rows, map_rows_numpy
from metadesign.design.discretize import AtomTable
from metadesign.design.phase import LensChannel

numba = pytest.importorskip("numba") if jit.enabled() else None
compiled_only = pytest.mark.skipif(not jit.enabled(), reason="numba not installed (or METADESIGN_JIT=0)")

CX, CY = paper_channels()


_compiled = jit.compiled  # a package kernel as a numba dispatcher, for the test's own compiled loops

def _atoms(n=24, seed=0) -> AtomTable:
    """A random birefringent library: phases anywhere on the torus, some of them tied at +-pi."""
    rng = np.random.default_rng(seed)
    ph = rng.uniform(-np.pi, np.pi, (n, 2))
    ph[0] = [np.pi, -np.pi]  # the seam: angle() can return either end
    amp = rng.uniform(0.6, 1.0, (n, 2))
    t = amp * np.exp(1j * ph)
    return AtomTable(wx=rng.uniform(1e-7, 4e-7, n), wy=rng.uniform(1e-7, 4e-7, n), t=t, T0=amp ** 2,
                     lib_index=np.zeros((n, 2), int), n_empty_bins=0, n_kept_cells=n, tn_scale=1.0)


@compiled_only
def test_wrap_is_numpys_float_for_float():
    """The Cody-Waite wrap of the kernel against numpy's fmod-based ``(v + pi) % 2pi - pi`` (bit patterns
    compared, signed zeros and exact multiples of 2 pi included, up to 1e9 rad and beyond its range)."""
    from metadesign.design.kernel import _wrap

    _wrap = _compiled(_wrap)
    rng = np.random.default_rng(3)
    parts = [rng.uniform(-s, s, 200_000) for s in (1e-300, 1e-9, 1.0, math.pi, 7.0, 1e3, 1e5, 1e7, 1e9)]
    k = np.arange(-2000, 2000, dtype=float)
    seam = k * (2 * math.pi) - math.pi
    parts += [seam, np.nextafter(seam, np.inf), np.nextafter(seam, -np.inf), k * (2 * math.pi),
              np.array([0.0, -0.0, math.pi, -math.pi, 2 ** 60, -(2 ** 60), np.inf, -np.inf, np.nan])]
    a = np.concatenate(parts)
    with np.errstate(invalid="ignore"):
        ref = (a + np.pi) % (2 * np.pi) - np.pi
    out = np.empty_like(a)

    @numba.njit
    def run(a, out):
        for i in range(a.size):
            out[i] = _wrap(a[i])

    run(a, out)
    same = (out.view(np.int64) == ref.view(np.int64)) | (np.isnan(out) & np.isnan(ref))
    assert same.all(), a[~same][:5]


@compiled_only
@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 127, 128, 129, 255, 256, 1000, 8193, 100_003, 1_234_567])
def test_pairwise_sum_is_numpys(n):
    """The kernel sums its terms as numpy's ``np.sum`` does (blocks of 128 with 8 accumulators, split at
    ``n // 2`` rounded down to 8): the same float for any length."""
    from metadesign.design.kernel import _block_sum, _combine, _leaves

    _block_sum, _combine, _leaves = map(_compiled, (_block_sum, _combine, _leaves))

    @numba.njit
    def pairwise(a):
        leaves = _leaves(a.size)
        sums = np.zeros(leaves.size)
        p = 0
        for i in range(leaves.size):
            sums[i] = _block_sum(a[p:p + leaves[i]], leaves[i])
            p += leaves[i]
        return _combine(sums, a.size) if a.size else 0.0

    a = np.random.default_rng(n).standard_normal(n) ** 2 * 1e3
    assert pairwise(a) == np.sum(a)
    assert sum(_leaves(n)) == n


def _check(spec, atoms, offsets, rows, cols=None):
    mapper = NearestAtom(atoms, Metric.PHASE, grid=256)
    dtype, empty = (np.uint8, 255) if spec.bounded else (np.uint8, None)
    c0, c1 = cols or (0, spec.n_cells)
    got = map_rows(spec, atoms, mapper, offsets, dtype, empty, *rows, c0, c1)
    ref = map_rows_numpy(spec, atoms, mapper, offsets, dtype, empty, *rows, c0, c1)
    np.testing.assert_array_equal(got[0], ref[0])
    for a, b in zip(got[1], ref[1]):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # exact: the same floats
    assert mapper.unsafe_fraction > 0  # the candidates' path is exercised
    return got


@compiled_only
@pytest.mark.parametrize("case", ["square", "circle", "polygon", "zernike", "block"])
def test_design_kernel_is_the_numpy_twin(case):
    """The compiled discretizer maps every cell onto the atom numpy maps it to and sums the same
    errors and efficiencies bit for bit: a full square, a circular and a polygonal clear aperture, lenses
    with Zernike terms (their phase from numpy), a column block off the origin, offsets on both axes."""
    atoms = _atoms()
    n = 301
    kw = {"circle": {"circular_aperture": True},
          "polygon": {"aperture_wkt": "POLYGON ((-1e-4 -1e-4, 1e-4 -0.5e-4, 0.3e-4 1e-4, -1e-4 -1e-4))"}}
    cx, cy = CX, CY
    if case == "zernike":
        cx = tuple(dataclasses.replace(c, zernike=((5, 0.4), (8, -0.3)), radius=n * 0.7e-6 / 2) for c in CX)
        kw = {case: {"circular_aperture": True}}
    spec = SupercellSpec(1.55e-6, 0.7e-6, n, 2, cx, cy, **kw.get(case, {}))
    rows, cols = ((40, 229), (17, 260)) if case == "block" else ((0, n), None)
    got = _check(spec, atoms, (0.37, -1.1), rows, cols)
    if case != "square":
        assert 0 < got[1][3] < (rows[1] - rows[0]) * n  # some cells outside the aperture
    # no offsets (the kernel must not add a 0.0 numpy never adds) and a large phase range (f = 2 mm)
    lens = LensChannel(2e-3, 3e-5, -2e-5)
    spec2 = SupercellSpec(1.55e-6, 0.7e-6, 150, 1, (lens,), (dataclasses.replace(lens, focal_length=2.1e-3),))
    _check(spec2, atoms, (0.0, 0.0), (0, 150))


@compiled_only
def test_oasis_kernel_is_the_numpy_twin():
    """The compiled encoder writes the numpy twin's bytes for random tiles (empty cells, one pillar,
    every cell one atom, long gaps between an atom's pillars) and for a tile with no pillar."""
    from metadesign.layouts.kernel import tile_records_kernel
    from metadesign.layouts.tiled import tile_records_numpy

    class Plan:  # what the numpy twin reads of a TiledPlan
        atoms = range(40)
        p_nm, x0 = 700, -1234567

    rng = np.random.default_rng(5)
    cases = [rng.integers(0, 40, (64, 96)), np.full((8, 8), 255), np.full((5, 7), 3)]
    sparse = np.full((200, 300), 255)
    sparse[rng.integers(0, 200, 50), rng.integers(0, 300, 50)] = rng.integers(0, 40, 50)
    one = np.full((9, 9), 255)
    one[4, 6] = 39
    mixed = rng.integers(0, 40, (128, 128))
    mixed[rng.random(mixed.shape) < 0.3] = 255
    for blk in cases + [sparse, one, mixed]:
        for dt in (np.uint8, np.uint16):
            b = blk.astype(dt)
            if dt is np.uint16:
                b[b == 255] = 65535
            for r0, c0 in ((0, 0), (4096, 70_000)):
                assert tile_records_kernel(b, r0, c0, 40, Plan.p_nm, Plan.x0) == tile_records_numpy(b, r0, c0, Plan)
    assert tile_records_kernel(np.full((4, 4), 255, np.uint8), 0, 0, 40, 700, 0) == b""


def test_numpy_path_when_disabled(monkeypatch):
    """``METADESIGN_JIT=0`` runs the numpy twins (what a machine without numba runs): the compiled
    kernels are not called."""
    import metadesign.design.build as build
    import metadesign.layouts.tiled as tiled

    def refuse(*a, **k):
        raise AssertionError("compiled kernel called")

    monkeypatch.setattr(build, "map_rows_kernel", refuse)
    monkeypatch.setattr(tiled, "tile_records_kernel", refuse)
    monkeypatch.setenv("METADESIGN_JIT", "0")
    atoms = _atoms()
    spec = SupercellSpec(1.55e-6, 0.7e-6, 40, 2, CX, CY)
    blk, _ = map_rows(spec, atoms, NearestAtom(atoms, Metric.PHASE, grid=64), (0.0, 0.0), np.uint8, None, 0, 40)

    class Plan:
        atoms, p_nm, x0 = range(24), 700, 0

    assert tiled.tile_records(blk, 0, 0, Plan)
    monkeypatch.setenv("METADESIGN_JIT", "1")
    if numba is None:  # no numba here: the twins are the only path
        return
    with pytest.raises(AssertionError, match="compiled"):
        map_rows(spec, atoms, NearestAtom(atoms, Metric.PHASE, grid=64), (0.0, 0.0), np.uint8, None, 0, 40)


@compiled_only
@pytest.mark.parametrize("n,block,tile_blocks", [(64, 8, 3), (70, 6, 4), (33, 4, 1)])
def test_pupil_block_sums_are_the_einsum_twin(n, block, tile_blocks, monkeypatch):
    """The coarse pupil's compiled block sums (one pass per row tile, complex128 per block) against the
    numpy einsum of the padded tile (METADESIGN_JIT=0): the same pupil to float32 rounding, ragged last
    blocks and row tiles included."""
    from metadesign.sensing.forward import coarse_pupil

    rng = np.random.default_rng(n)
    t = (rng.standard_normal((n, n, 2)) + 1j * rng.standard_normal((n, n, 2))).astype(np.complex64)

    def rows(r0, r1):
        return t[r0:r1], 0

    args = (rows, n, 0.7e-6, 1.55e-6, 2e-3, block, 2, 0.83, tile_blocks)
    got = coarse_pupil(*args).G
    monkeypatch.setenv("METADESIGN_JIT", "0")
    ref = coarse_pupil(*args).G
    assert np.abs(ref).max() > 0.1
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6 * np.abs(ref).max())
    share = coarse_pupil(*args, block_rows=(1, 3)).G  # a worker's share: its block rows of the whole
    np.testing.assert_allclose(share, ref[:, :, 1:3], rtol=0, atol=2e-6 * np.abs(ref).max())


@compiled_only
def test_pillar_lookup_is_numpys_fancy_index(monkeypatch):
    """The nominal device's per-pillar look-up (compiled) equals numpy's ``table[where(im < 0, A, im)]``."""
    from metadesign.library.store import load_library
    from metadesign.sensing.transmission import pillar_transmission

    from conftest import REPO

    lib = load_library(REPO / "library" / "paper.npz")
    rng = np.random.default_rng(2)
    widths = np.stack([rng.uniform(lib.wx[1], lib.wx[-2], 30), rng.uniform(lib.wy[1], lib.wy[-2], 30)], 1) * 1e9
    im = rng.integers(-1, 30, (37, 53)).astype(np.int16)
    got, c1 = pillar_transmission(im, widths, lib, rows=slice(3, 31))
    monkeypatch.setenv("METADESIGN_JIT", "0")
    ref, c2 = pillar_transmission(im, widths, lib, rows=slice(3, 31))
    assert got.dtype == ref.dtype and c1 == c2 == 0
    np.testing.assert_array_equal(got, ref)
