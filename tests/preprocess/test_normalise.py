"""Background normalisation helpers (module sonarmap.preprocess.normalise)."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from sonarmap.preprocess.normalise import estimate_background, expand_grid


def _bilinear_reference(grid: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Float64 bilinear interpolation from block centres, edges held (dense weight matrices)."""

    def weights(n: int, nb: int) -> np.ndarray:
        x = np.clip((np.arange(n) + 0.5) * nb / n - 0.5, 0, nb - 1)
        i0 = np.minimum(np.floor(x).astype(int), max(nb - 2, 0))
        i1 = np.minimum(i0 + 1, nb - 1)
        w = np.zeros((n, nb))
        np.add.at(w, (np.arange(n), i0), 1 - (x - i0))
        np.add.at(w, (np.arange(n), i1), x - i0)
        return w

    return weights(shape[0], grid.shape[0]) @ grid.astype(np.float64) @ weights(shape[1], grid.shape[1]).T


@pytest.mark.parametrize(("grid_shape", "shape"), [((16, 16), (703, 256)), ((16, 3), (2000, 48)),
                                                   ((1, 1), (40, 30)), ((5, 1), (40, 30)), ((1, 7), (9, 64)),
                                                   ((2, 2), (4, 3))])
def test_expand_grid_is_bilinear_and_independent_of_blas_threads(grid_shape, shape) -> None:
    grid = np.random.default_rng(0).uniform(0.5, 2.0, grid_shape).astype(np.float32)
    out = expand_grid(grid, shape)
    assert out.dtype == np.float32 and out.shape == shape and out.flags.c_contiguous
    np.testing.assert_allclose(out, _bilinear_reference(grid, shape), rtol=0, atol=1e-6)
    # block centres are reproduced and the corners held
    assert out[0, 0] == pytest.approx(grid[0, 0], abs=1e-6)
    assert out[-1, -1] == pytest.approx(grid[-1, -1], abs=1e-6)
    with threadpool_limits(1):
        assert np.array_equal(expand_grid(grid, shape), out)
    buf = np.full(shape, np.nan, dtype=np.float32)
    assert expand_grid(grid, shape, out=buf) is buf and np.array_equal(buf, out)


def _images(rng: np.random.Generator, n: int, m: int) -> list[np.ndarray]:
    """8-bit images (the readers' level x float32(1/255) and level / 255), float and tied data."""
    levels = rng.integers(0, 256, (n, m))
    return [levels.astype(np.float32) * np.float32(1.0 / 255.0), levels.astype(np.float32) / np.float32(255.0),
            rng.exponential(size=(n, m)).astype(np.float32), np.round(rng.random((n, m)) * 4).astype(np.float32) - 1]


@pytest.mark.parametrize("shape", [(1, 1), (3, 2), (40, 5), (2000, 48), (703, 256), (17, 300)])
def test_selection_kernels_equal_numpys_order_statistics(shape) -> None:
    """The numba order statistics of the background estimate equal numpy's and scipy's, bit for bit."""
    from scipy.ndimage import median_filter

    from sonarmap.preprocess._kernels import median5, median_inplace, percentiles_linear, row_quartile_u8
    from sonarmap.preprocess.normalise import _Q10_90, _row_quartile

    rng = np.random.default_rng(shape[0] * 1000 + shape[1])
    n, m = shape
    k = (m - 1) // 4
    for t, img in enumerate(_images(rng, n, m)):
        ref = np.sort(np.maximum(img, 0.0), axis=1)[:, k]
        out, ok = row_quartile_u8(img, k)
        assert ok or t >= 2  # 8-bit data is counted (either scaling), the rest sorted
        if ok:
            assert np.array_equal(out, ref)
        assert _row_quartile(img).tobytes() == ref.tobytes()
        flat = img.ravel()
        assert median5(flat).tobytes() == median_filter(flat, size=5, mode="nearest").tobytes()
        for x in (flat, flat.astype(np.float64), flat[: max(flat.size - 1, 1)]):
            assert np.float64(median_inplace(x.copy(), x.size)) == np.float64(np.median(x))
            if x.size >= 2:
                assert percentiles_linear(x, _Q10_90).tobytes() == np.percentile(x, [10, 90]).tobytes()


def test_median5_network_takes_the_middle_value_of_every_tie_pattern() -> None:
    import itertools

    from sonarmap.preprocess._kernels import median5

    for t in itertools.product(range(5), repeat=5):
        x = np.array(t, dtype=np.float32)
        assert median5(x)[2] == np.sort(x)[2]


def _smooth_reference(log_level: np.ndarray, width: int, floor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numpy form of smooth_log_level: rounds of scipy uniform_filter1d / np.median, the rows
    without support interpolated with np.interp, the rows left out grown over their flanks."""
    from scipy.ndimage import uniform_filter1d

    n = log_level.size
    keep, smooth, above = np.ones(n), log_level.copy(), np.zeros(n, bool)
    rows = np.arange(n)
    for _ in range(10):
        den = uniform_filter1d(keep, width, mode="nearest")
        num = uniform_filter1d(log_level * keep, width, mode="nearest")
        ok = den > 0.05
        smooth = np.where(ok, num / np.maximum(den, 1e-12), smooth)
        if ok.any() and not ok.all():
            smooth[~ok] = np.interp(rows[~ok], rows[ok], smooth[ok])
        resid = log_level - smooth
        s = np.maximum(1.4826 * float(np.median(np.abs(resid[keep > 0]))) if np.any(keep > 0) else 0.0, floor)
        new = resid > 2.5 * s
        for i in range(1, n):
            new[i] |= new[i - 1] and resid[i] > 0.5 * s[i]
        for i in range(n - 2, -1, -1):
            new[i] |= new[i + 1] and resid[i] > 0.5 * s[i]
        changed = not np.array_equal(new, above)
        above = new
        keep = (~above).astype(np.float64)
        if not changed:
            break
    return _bridge_reference(log_level, keep, width, smooth), above


def _bridge_reference(y: np.ndarray, keep: np.ndarray, width: int, smooth: np.ndarray) -> np.ndarray:
    """The numpy form of _bridge_left_out: each stretch of rows whose window (uniform_filter1d,
    mode "nearest") holds a row left out takes the least-squares quadratic through the kept rows
    within 2 windows of it on either side, when each side holds >= width // 2 of them, bounded
    by the curve above and by the lower of its values beside the stretch below."""
    from scipy.ndimage import uniform_filter1d

    n = y.size
    out = smooth.copy()
    short = uniform_filter1d(keep, width, mode="nearest") < 1.0 - 1e-9
    edges = np.flatnonzero(np.diff(np.r_[0, short.astype(int), 0]))
    for a, b in zip(edges[::2], edges[1::2]):
        lo, hi = max(a - 2 * width, 0), min(b + 2 * width, n)
        if keep[lo:a].sum() < width // 2 or keep[b:hi].sum() < width // 2:
            continue
        k = np.r_[np.arange(lo, a), np.arange(b, hi)]
        k = k[keep[k] > 0]
        c0, sc = 0.5 * (a + b - 1), 1.0 / (hi - lo)
        q = np.polynomial.polynomial.polyfit((k - c0) * sc, y[k], 2)
        fit = np.polynomial.polynomial.polyval((np.arange(a, b) - c0) * sc, q)
        out[a:b] = np.minimum(np.maximum(fit, min(smooth[a - 1], smooth[b])), smooth[a:b])
    return out


def test_smoothing_and_background_rows_equal_the_numpy_reference() -> None:
    """smooth_log_level = its numpy reference (above); background_rows = the medians over the first
    rows of a stable argsort (ties included)."""
    from sonarmap.preprocess._kernels import background_rows, smooth_log_level

    rng = np.random.default_rng(4)
    for n, width in ((2000, 125), (703, 43), (512, 32), (20, 15), (16, 15)):
        log_level = np.log(np.round(rng.lognormal(size=n) * 20) / 20 + 0.05)
        log_level[n // 3: n // 3 + 5] += 3.0  # a surface across the fan
        log_level[n // 2: n // 2 + width] += 1.0  # a wide one (no support left in its middle)
        floor = np.full(n, 0.02) if n % 2 else 0.02 + rng.random(n)
        smooth, above = _smooth_reference(log_level, width, floor)
        s, a = smooth_log_level(log_level, width, floor)
        assert np.allclose(s, smooth, rtol=0, atol=1e-9) and np.array_equal(a, above)
        q50 = np.round(rng.random(n) * 8).astype(np.float32).astype(np.float64)  # many ties
        q25 = q50 - rng.random(n)
        for n_rows in (1, n // 4, n):
            rows = np.argsort(q50, kind="stable")[:n_rows]
            assert background_rows(q25, q50, n_rows) == (np.median(q50[rows]), np.median((q50 - q25)[rows]))


def test_a_surface_across_every_beam_is_left_out_of_the_level_with_its_flanks() -> None:
    """A seabed-like echo over all beams (2.5x the background at its peak, Gaussian over +-15
    rows) raises the estimated level under it by < 5 % (its flanks are left out with its core,
    and the curve is bridged across the rows left out by a quadratic through the kept rows on
    either side: measured 3.6 %; with a straight line between the running means at the stretch's
    ends 8.7 %, with the flanks kept 31 %), and nowhere else moves it by more than 1.5 % (measured
    0.9 %)."""
    rng = np.random.default_rng(3)
    n, m = 1000, 48
    r = np.arange(n)
    b = 0.4 * np.exp(-r / 1500.0)
    speckle = rng.gamma(4.0, 0.25, size=(n, m))
    bump = 1.0 + 1.5 * np.exp(-0.5 * ((r - 630) / 15.0) ** 2)
    empty = (b[:, None] * speckle).astype(np.float32)
    floor = (b[:, None] * bump[:, None] * speckle).astype(np.float32)
    dev = estimate_background(floor)[0].level_by_bin / estimate_background(empty)[0].level_by_bin - 1.0
    assert dev[560:700].max() < 0.05
    assert np.abs(np.r_[dev[:540], dev[720:]]).max() < 0.015


def test_a_seabed_filling_most_blocks_leaves_the_water_columns_beam_factor_at_one() -> None:
    """A seabed 8x the background on every beam from an arc at 40-55 % of the window to its end
    (more than half of the beam factor's blocks) leaves the factor of the water column in front of
    it at ~1: it is normalised by the median of the background blocks, not of all of them (before:
    0.5, the clip, so the water column was doubled in the measured image), and the seabed's own
    blocks stay above 1."""
    rng = np.random.default_rng(5)
    n, m = 800, 256
    rows = np.arange(n)[:, None]
    start = (0.40 + 0.15 * (np.linspace(-1.0, 1.0, m) ** 2))[None, :] * n  # an arc: nearest mid-fan
    level = np.where(rows >= start, 8.0, 1.0)
    img = (0.03 * level * rng.gamma(10.0, 0.1, size=(n, m))).astype(np.float32)
    bg = estimate_background(img)[0]
    full = expand_grid(bg.beam_factor, img.shape)
    front = rows[:, 0] < 0.35 * n
    assert np.median(full[front]) == pytest.approx(1.0, abs=0.1), np.median(full[front])
    assert np.median(full[rows[:, 0] > 0.7 * n]) > 1.5


def test_a_band_across_the_fan_leaves_the_beam_factor_at_one_and_a_step_keeps_it() -> None:
    """A faint band across every beam (1.6x the background over 60 of 1000 rows, a seabed seen
    at grazing incidence) is no beam pattern: the beam factor's block row holding it stays at 1
    (measured median 0.999; 1.54 before the block rows' medians were median filtered along range,
    which raised the background under the band and put its leading edges early).  A seabed that
    fills the window to its end (8x from row 700 on) keeps its factor behind the step (2.0, the
    clip), and the water column in front stays at 1."""
    rng = np.random.default_rng(7)
    n, m = 1000, 128
    r = np.arange(n)[:, None]
    b = 0.4 * np.exp(-r / 1500.0)
    speckle = rng.gamma(8.0, 1 / 8.0, size=(n, m))
    band = (b * np.where((r >= 620) & (r < 680), 1.6, 1.0) * speckle).astype(np.float32)
    f = np.median(estimate_background(band)[0].beam_factor, axis=1)
    assert f.size == 16 and np.abs(f - 1.0).max() < 0.03, f
    step = (b * np.where(r >= 700, 8.0, 1.0) * speckle).astype(np.float32)
    f = np.median(estimate_background(step)[0].beam_factor, axis=1)
    assert np.abs(f[:11] - 1.0).max() < 0.03 and np.all(f[12:] > 1.5), f


def test_the_level_sigma_floor_is_one_quantisation_step_on_8bit_data() -> None:
    """On a dim 8-bit background (a few levels) one step of the row quartile is no surface."""
    from sonarmap.preprocess.normalise import LEVEL_SIGMA_FLOOR, _sigma_floor

    level = np.array([2.0, 8.0, 100.0]) / 255.0
    assert np.allclose(_sigma_floor(level, True), [np.log(1.5), np.log(1.125), LEVEL_SIGMA_FLOOR])
    assert np.all(_sigma_floor(level, False) == LEVEL_SIGMA_FLOOR)


def _on_8bit_grid_reference(img: np.ndarray) -> bool:
    """The numpy form of on_8bit_grid: every positive value of a sample is a multiple of 1/255."""
    flat = img.ravel()
    sample = flat[:: max(flat.size // 4096, 1)]
    pos = sample[sample > 0]
    if pos.size == 0:
        return True
    scaled = pos * np.float32(255.0)
    with np.errstate(invalid="ignore"):
        return bool(np.all(np.abs(scaled - np.rint(scaled)) < 1e-3))


def test_on_8bit_grid_kernel_equals_the_numpy_test() -> None:
    """The one-pass kernel answers as the numpy test on 8-bit, float, thresholded, transposed and
    non-finite images, float32 and float64, with values just on and just off the 1e-3 tolerance."""
    from sonarmap.preprocess.normalise import on_8bit_grid

    rng = np.random.default_rng(8)
    answers = set()
    for it in range(1200):
        shape = (int(rng.integers(1, 300)), int(rng.integers(1, 200)))
        dtype = (np.float32, np.float64)[it % 2]
        img = (rng.integers(0, 256, shape) / 255).astype(dtype)
        kind = it % 7
        if kind == 1:
            img = rng.random(shape).astype(dtype)
        elif kind == 2:
            img.flat[rng.integers(0, img.size)] += dtype(rng.choice([1e-3, 0.99e-3, 1.01e-3, 0.5]) / 255)
        elif kind == 3:
            img.flat[rng.integers(0, img.size, 3)] = rng.choice([np.nan, np.inf, -np.inf, -1.0])
        elif kind == 4:
            img[:] = 0
        elif kind == 5:
            img = img.T
        elif kind == 6:
            img[rng.random(shape) < 0.6] = 0  # thresholded (DIDSON-like)
        expected = _on_8bit_grid_reference(img)
        assert on_8bit_grid(img) is expected
        answers.add(expected)
    assert answers == {True, False}


@functools.cache
def _pooled_ratio_reference():
    """The one-row-at-a-time form of the pooled ratio (scipy's uniform_filter(img / level / factor,
    pool, mode="nearest") in float64 running sums stored as float32), jitted (once per process:
    not cached on disk, so that it never keeps old code)."""
    from numba import njit

    @njit
    def running_mean(src, dst, size):
        n, h, s = src.shape[0], size // 2, 0.0
        for k in range(-h, size - h):
            s += src[min(max(k, 0), n - 1)]
        for i in range(n):
            dst[i] = s / size
            s += src[min(max(i - h + size, 0), n - 1)] - src[min(max(i - h, 0), n - 1)]

    @njit
    def pooled(img, level, factor, pool_r, pool_c):
        n, m = img.shape
        z = np.empty((n, m), np.float32)
        for i in range(n):
            for j in range(m):
                z[i, j] = img[i, j] * (1.0 / level[i]) / factor[i, j]
        tmp = np.empty((n, m), np.float32)
        for j in range(m):
            running_mean(z[:, j].copy(), tmp[:, j], pool_r)
        for i in range(n):
            running_mean(tmp[i].copy(), z[i], pool_c)
        return z

    return pooled


@pytest.mark.parametrize("shape", [(2000, 48), (703, 256), (1, 1), (3, 2), (7, 5), (9, 64), (33, 17)])
def test_pooled_ratio_grid_equals_the_ratio_to_the_expanded_grid(shape) -> None:
    """pooled_ratio_grid (factor interpolated on the way, 4 rows per beam pass) gives the bits of
    pooled_ratio with the factor expand_grid makes, for any pool, grid and row count (n % 4), and
    a grid of one block of 1 the bits of no factor."""
    from sonarmap.preprocess._kernels import pooled_ratio, pooled_ratio_grid
    from sonarmap.preprocess.normalise import _ONE_BLOCK, _grid_rows

    reference = _pooled_ratio_reference()

    rng = np.random.default_rng(shape[0] * 7 + shape[1])
    n, m = shape
    for t in range(6):
        img = _images(rng, n, m)[t % 3]
        level = rng.uniform(0.01, 3.0, n).astype(np.float32)
        grid = rng.uniform(0.5, 2.0, (int(rng.integers(1, 17)), int(rng.integers(1, 17)))).astype(np.float32)
        pool = (int(rng.integers(1, min(n, 9) + 1)), int(rng.integers(1, min(m, 7) + 1)))
        z, work = np.empty((n, m), np.float32), np.empty((n, m), np.float32)
        for g, full in ((grid, expand_grid(grid, shape)), (_ONE_BLOCK, np.ones(shape, np.float32))):
            pooled_ratio_grid(img, level, *_grid_rows(g, shape), *pool, z, work)
            assert z.tobytes() == pooled_ratio(img, level, full, *pool).tobytes()
            assert z.tobytes() == reference(img, level, full, *pool).tobytes()


def _background_quartiles_reference(z: np.ndarray) -> tuple[float, float]:
    """Step 4's ``(c50, spread)`` the plain numpy way: every row sorted, a stable argsort of the
    medians, np.median."""
    n, m = z.shape
    rows = np.sort(z, axis=1)
    q25, q50 = rows[:, (m - 1) // 4].astype(np.float64), rows[:, (m - 1) // 2].astype(np.float64)
    sel = np.argsort(q50, kind="stable")[: max(n // 4, 1)]
    return float(np.median(q50[sel])), float(np.median((q50 - q25)[sel]))


@pytest.mark.parametrize("shape", [(4096, 512), (703, 256), (2000, 48), (40, 512), (3, 600), (1, 513), (257, 1024),
                                   (64, 1500)])
@pytest.mark.parametrize("partition_min", [None, 1, 1 << 30])
def test_background_quartiles_equal_the_sorted_ones(shape, partition_min, monkeypatch) -> None:
    """Long rows partitioned (the lower quartile only in the background rows), and only the rows
    that can be background rows ordered, give the sorted rows' (c50, spread), with ties, zeros and
    non-finite values (which fall back to ordering every row) and a sample of rows unlike the
    others (whose threshold falls short)."""
    from sonarmap.preprocess import normalise

    if partition_min is not None:
        monkeypatch.setattr(normalise, "_PARTITION_MIN", partition_min)
    rng = np.random.default_rng(shape[0] + shape[1])
    for t in range(6):
        z = rng.exponential(size=shape).astype(np.float32)
        if t == 1:
            z = np.round(z * 4) / 4  # many ties
        elif t == 2:
            z[rng.random(shape) < 0.3] = 0
        elif t == 3:
            z.flat[rng.integers(0, z.size, 50)] = np.inf
        elif t == 4:
            z[: max(shape[0] // 2, 1)] = np.nan
        elif t == 5:
            z[:: normalise._SAMPLE_STEP] *= np.float32(0.25)  # the sampled rows lowest
        with np.errstate(invalid="ignore"):
            expected = _background_quartiles_reference(z)
        got = normalise._background_quartiles(z)
        assert np.array(got).tobytes() == np.array(expected).tobytes()


def test_candidate_rows_hold_the_lowest_medians() -> None:
    """The rows left for ordering hold every row whose median is among the quarter lowest (ties
    included), in ascending order; a sample unlike the other rows gives None."""
    from sonarmap.preprocess import normalise

    rng = np.random.default_rng(5)
    z = rng.exponential(size=(1000, 64)).astype(np.float32)
    z[rng.random(1000) < 0.5] *= np.float32(3.0)
    med = np.sort(z, axis=1)[:, 31]
    rows = normalise._candidate_rows(z, 31, 250)
    assert rows is not None and 250 <= rows.size < 1000 and np.all(np.diff(rows) > 0)
    assert set(np.flatnonzero(med <= np.sort(med)[249])) <= set(rows.tolist())
    z[:: normalise._SAMPLE_STEP] *= np.float32(0.1)
    assert normalise._candidate_rows(z, 31, 250) is None


def test_row_quartile_of_scaled_levels_equals_the_general_count() -> None:
    """The readers' 8-bit form (level x float32(1/255)) counted without a value table gives the
    general count's answer and bits; a value off that form anywhere (the other scaling, above 1,
    the 256th level's multiple, a float) hands the image to the general count, which decides."""
    from sonarmap.preprocess._kernels import _row_quartile_levels, _row_quartile_scaled, row_quartile_u8

    rng = np.random.default_rng(11)
    step = np.float32(1.0 / 255.0)
    odd = [np.float32(1.0) + np.float32(1e-7), np.float32(256) * step, np.float32(3) / np.float32(255),
           np.float32(0.3), np.float32(-0.0), np.float32(-2.0), np.float32(np.nan), np.float32(1.0)]
    taken = set()
    for t in range(400):
        n, m = int(rng.integers(1, 60)), int(rng.integers(1, 300))
        img = rng.integers(0, 256, (n, m)).astype(np.float32) * step
        if t % 4 == 3:
            img = rng.integers(0, 256, (n, m)).astype(np.float32) / np.float32(255.0)  # the other scaling
        elif t % 2:
            img.flat[rng.integers(0, img.size, int(rng.integers(1, 4)))] = rng.choice(odd)
        k = int(rng.integers(0, m))
        out, ok = row_quartile_u8(img, k)
        ref, ref_ok = _row_quartile_levels(img, k)
        assert ok == ref_ok
        if ok:
            assert out.tobytes() == ref.tobytes()
            assert out.tobytes() == np.sort(np.where(img > 0, img, np.float32(0)), axis=1)[:, k].tobytes()
        taken.add((ok, bool(_row_quartile_scaled(img, k, np.empty(n, np.float32)))))
    assert taken == {(True, True), (True, False), (False, False)}


def test_level_tail_equals_the_numpy_steps() -> None:
    """level_tail: the ring-down rows keep their level, then at most max_rise x the running
    minimum, numpy's float32 steps bit for bit (Python and numpy float64 factors, off for 0)."""
    from sonarmap.preprocess._kernels import level_tail

    rng = np.random.default_rng(12)
    for t in range(300):
        n = int(rng.integers(1, 400))
        smooth = np.exp(rng.normal(size=n))
        level = np.exp(rng.normal(size=n)).astype(np.float32).astype(np.float64)
        above = rng.random(n) < 0.3
        above[: int(rng.integers(0, 5))] = True
        if t % 5 == 0:
            above[:] = t % 10 == 0
        max_rise = (2.0, 1.3, np.float64(1.7), 0.0, 2.1)[t % 5]
        out = smooth.copy()
        if above.any():
            lead = int(np.argmin(above)) if not above.all() else n
            out[:lead] = level[:lead]
        out = out.astype(np.float32)
        if max_rise > 0:
            out = np.minimum(out, max_rise * np.minimum.accumulate(out)).astype(np.float32)
        rise = np.result_type(max_rise, np.float32).type(max_rise)
        assert level_tail(smooth, level, above, rise, max_rise > 0).tobytes() == out.tobytes()


def test_median_inplace_equals_numpys_median_with_ties() -> None:
    """median_inplace (the lower middle value as the maximum of the lower half left by the
    selection) equals np.median on even and odd sizes, many ties, float32 and float64."""
    from sonarmap.preprocess._kernels import median_inplace

    rng = np.random.default_rng(13)
    for t in range(2000):
        n = int(rng.integers(1, 300))
        x = rng.normal(size=n)
        if t % 3 == 0:
            x = np.round(x * 2)  # ties
        x = x.astype((np.float64, np.float32)[t % 2])
        assert np.float64(median_inplace(x.copy(), n)) == np.float64(np.median(x))


def test_median_inplace_of_many_values_equals_numpys_median() -> None:
    """From MEDIAN_BUCKET_MIN values on median_inplace takes the histogram route: np.median again,
    with the middle ranks at a bucket's edge, heavy tails that crowd one bucket, ties, constants,
    infinities and spans that overflow (those take quickselect)."""
    from sonarmap.preprocess._kernels import MEDIAN_BUCKET_MIN, median_inplace

    rng = np.random.default_rng(17)
    for t in range(600):
        n = int(rng.integers(MEDIAN_BUCKET_MIN, 3000))
        x = np.abs(rng.standard_t(1 + t % 4, size=n))
        if t % 3 == 0:
            x = np.round(x * 4) / 4  # ties
        if t % 7 == 0:
            x[: n // 2] = 0.0  # the upper middle value the first of its bucket
        if t % 11 == 0:
            x[:] = 1.5
        if t % 13 == 0:
            x[rng.integers(0, n, 3)] = (np.inf, -np.inf, 1e308)[t % 3]
        if t % 17 == 0:
            x[:2] = (-1e308, 1e308)
        x = x.astype((np.float64, np.float32)[t % 2])
        assert np.float64(median_inplace(x.copy(), n)) == np.float64(np.median(x))


@pytest.mark.parametrize("n_levels", [256, 64, 2, 300])
def test_normalised_levels_are_the_quantised_normalised_image(n_levels) -> None:
    """The levels the background estimate makes on the way are :func:`quantize` of its normalised
    image (round binning) for up to 256 levels, bit for bit, also after the gain is lowered for a
    saturated image; none for more levels, nor where nothing is normalised."""
    from sonarmap.preprocess.normalise import estimate_background_levels, estimate_background
    from sonarmap.stats.mixture import quantize

    rng = np.random.default_rng(n_levels)
    for t in range(4):
        img = rng.exponential(size=(300, 40)).astype(np.float32) * np.float32(0.05)
        if t == 1:
            img[100:160] *= 60.0  # > 1 % of the pixels at the top level: the gain is lowered
        if t == 2:
            img[rng.random(img.shape) < 0.5] = 0.0  # thresholded: not normalised
        bg, u, levels = estimate_background_levels(img, n_levels=n_levels)
        u_public = estimate_background(img)[1]
        assert (u is None) == (u_public is None) and (u is None or u.tobytes() == u_public.tobytes())
        if u is None or n_levels > 256:
            assert levels is None
            continue
        assert levels.dtype == np.uint8 and np.array_equal(levels, quantize(u, n_levels))


def _numpy_block_quartiles(img, level, nr, nc, br, bc, k):
    """The beam-factor blocks' k-th smallest ratio as numpy computes it (gather, partition)."""
    ratio = (img[: nr * br, : nc * bc] / level[: nr * br, None]).astype(np.float32)
    blocks = ratio.reshape(nr, br, nc, bc).transpose(0, 2, 1, 3).reshape(nr * nc, br * bc)
    return np.partition(blocks, k, axis=1)[:, k]


@pytest.mark.parametrize("case", ["8bit", "float", "ties", "zero_level", "negative", "constant", "tiny_spread",
                                  "signed_zero"])
def test_block_quartiles_equal_numpys_partition(case) -> None:
    """The beam-factor kernel selects exactly np.partition's order statistic, NaN (0/0 on a zero
    level) sorted last and infinities kept, on every kind of block (it would differ if a value's
    histogram bucket were computed differently in its two passes)."""
    from sonarmap.preprocess._kernels import QUARTILE_BUCKETS, block_quartiles

    rng = np.random.default_rng(7)
    n, m, nr, nc = 203, 64, 7, 4
    br, bc = n // nr, m // nc
    img = {"8bit": rng.integers(0, 256, (n, m)) / np.float32(255.0),
           "float": rng.gamma(2.0, 1.0, (n, m)), "ties": rng.integers(0, 3, (n, m)) / np.float32(2.0),
           "zero_level": rng.integers(0, 4, (n, m)) / np.float32(3.0),
           "negative": rng.normal(0.0, 1.0, (n, m)), "constant": np.full((n, m), 0.25),
           "tiny_spread": 1.0 + rng.integers(0, 2, (n, m)) * np.finfo(np.float32).eps,
           # -0.0 beside 0.0 (equal, other bits): the blocks' extremes from the float comparisons
           "signed_zero": np.where(rng.random((n, m)) < 0.5, -0.0, rng.integers(0, 3, (n, m)) / 2.0)}[case].astype(np.float32)
    level = rng.uniform(0.2, 2.0, n).astype(np.float32)
    if case == "zero_level":
        level[5:40] = 0.0  # 0/0 = NaN and x/0 = inf in the first blocks
    for k in (0, (br * bc - 1) // 4, br * bc - 1):
        got = block_quartiles(img, level, nr, nc, br, bc, k, np.empty((nc, br * bc), np.float32),
                              np.empty((4, QUARTILE_BUCKETS), np.int64))
        np.testing.assert_array_equal(got, _numpy_block_quartiles(img, level, nr, nc, br, bc, k))
