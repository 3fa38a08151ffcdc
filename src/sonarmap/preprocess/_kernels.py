"""numba kernels of :mod:`sonarmap.preprocess.normalise` (private to this package)."""

from __future__ import annotations

import numpy as np
from numba import njit, types
from numba.extending import overload

from sonarmap._histogram_kernels import add_partial_counts


@njit(cache=True, nogil=True, inline="always")
def _running_mean(src, dst, size):  # pragma: no cover - numba
    """``dst[i]`` = mean of ``src[i - size // 2 : i - size // 2 + size]``, edge samples repeated
    (scipy ``uniform_filter1d(mode="nearest")``, default origin)."""
    n = src.shape[0]
    h = size // 2
    s = 0.0
    for k in range(-h, size - h):
        s += src[min(max(k, 0), n - 1)]
    for i in range(n):
        dst[i] = s / size
        s += src[min(max(i - h + size, 0), n - 1)] - src[min(max(i - h, 0), n - 1)]


@njit(cache=True, nogil=True)
def pooled_ratio(img, level, factor, pool_r, pool_c):  # pragma: no cover - numba
    """``uniform_filter(img / (level[:, None] * factor), (pool_r, pool_c), mode="nearest")``.

    ``img`` and ``factor`` are float32 (n, m), ``level`` float32 (n,): separable running means,
    along range then across beams.
    """
    n, m = img.shape
    z = np.empty((n, m), dtype=np.float32)
    pooled_ratio_into(img, level, factor, pool_r, pool_c, z, np.empty((n, m), dtype=np.float32))
    return z


@njit(cache=True, nogil=True)
def pooled_ratio_into(img, level, factor, pool_r, pool_c, z, tmp):  # pragma: no cover - numba
    """:func:`pooled_ratio` written into ``z``, with ``tmp`` (float32, the image's shape) as work
    space: callers reuse both (fresh image-sized arrays cost page faults on every ping)."""
    n, m = img.shape
    for i in range(n):
        inv = 1.0 / level[i]
        for j in range(m):
            tmp[i, j] = img[i, j] * inv / factor[i, j]
    _pool_rows(tmp, pool_r, pool_c, z)


@njit(cache=True, nogil=True)
def pooled_ratio_grid(img, level, cols, r0, r1, fr, pool_r, pool_c, z, ratio):  # pragma: no cover - numba
    """:func:`pooled_ratio_into` with ``factor = interpolate_rows(cols, r0, r1, fr)`` interpolated
    on the way (the same float32 arithmetic), written into ``z``; ``ratio`` (float32, the image's
    shape) is work space: no image-sized factor array is written and read back.  The beam pass
    advances 4 rows' running sums together: each row's sum is a chain of dependent additions, whose
    latency bounds the one-row loop.
    """
    _grid_ratios(img, level, cols, r0, r1, fr, ratio)
    _pool_rows(ratio, pool_r, pool_c, z)


@njit(cache=True, nogil=True, error_model="numpy")
def _grid_ratios(img, level, cols, r0, r1, fr, ratio):  # pragma: no cover - numba
    """The ratios of :func:`pooled_ratio_grid` into ``ratio``; a zero level or factor raises
    ZeroDivisionError, as numba's default (Python) error model would.  Under that model each
    division by a varying divisor carries its own zero test, which keeps LLVM from vectorising the
    loop; here the tests come first, one per row (the loop 4-5x faster)."""
    n, m = img.shape
    one = np.float32(1.0)
    frow = np.empty(m, dtype=np.float32)
    for i in range(n):
        if level[i] == 0:
            raise ZeroDivisionError("division by zero")
        inv = 1.0 / level[i]
        f = fr[i]
        g = one - f
        a = cols[r0[i]]
        b = cols[r1[i]]
        zero = False
        for j in range(m):
            frow[j] = a[j] * g + b[j] * f
            zero |= frow[j] == 0
        if zero:
            raise ZeroDivisionError("division by zero")
        row = ratio[i]
        src = img[i]
        for j in range(m):
            row[j] = src[j] * inv / frow[j]


@njit(cache=True, nogil=True)
def _pool_rows(ratio, pool_r, pool_c, z):  # pragma: no cover - numba
    """The separable running means of :func:`pooled_ratio_into` of ``ratio`` into ``z`` (another
    array): along range by a running sum per beam, then across beams 4 rows at a time."""
    n, m = ratio.shape
    s = np.zeros(m)
    h = pool_r // 2
    for k in range(-h, pool_r - h):
        r = min(max(k, 0), n - 1)
        for j in range(m):
            s[j] += ratio[r, j]
    buf = np.empty((4, m), dtype=np.float32)
    sums = np.empty((4, m))
    i0 = 0
    while i0 < n:
        rows = min(4, n - i0)
        for t in range(rows):
            i = i0 + t
            a = ratio[min(max(i - h + pool_r, 0), n - 1)]
            b = ratio[min(max(i - h, 0), n - 1)]
            for j in range(m):
                buf[t, j] = s[j] / pool_r
                s[j] += a[j] - b[j]
        if rows == 4:
            _running_sums4(buf, sums, pool_c)
            for t in range(4):
                out = z[i0 + t]
                row = sums[t]
                for j in range(m):
                    out[j] = row[j] / pool_c
        else:
            for t in range(rows):
                _running_mean(buf[t], z[i0 + t], pool_c)
        i0 += rows


@njit(cache=True, nogil=True, inline="always")
def _running_sums4(buf, sums, size):  # pragma: no cover - numba
    """The running sums of :func:`_running_mean` (before its division by ``size``) of the 4 rows
    of ``buf`` into ``sums`` (float64), the 4 sums advanced together (the same additions per row)."""
    m = buf.shape[1]
    h = size // 2
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    for k in range(-h, size - h):
        c = min(max(k, 0), m - 1)
        s0 += buf[0, c]
        s1 += buf[1, c]
        s2 += buf[2, c]
        s3 += buf[3, c]
    for j in range(m):
        sums[0, j] = s0
        sums[1, j] = s1
        sums[2, j] = s2
        sums[3, j] = s3
        a = min(max(j - h + size, 0), m - 1)
        b = min(max(j - h, 0), m - 1)
        s0 += buf[0, a] - buf[0, b]
        s1 += buf[1, a] - buf[1, b]
        s2 += buf[2, a] - buf[2, b]
        s3 += buf[3, a] - buf[3, b]


@njit(cache=True, nogil=True)
def interpolate_rows(cols, r0, r1, fr):  # pragma: no cover - numba
    """``out[i] = (1 - fr[i]) cols[r0[i]] + fr[i] cols[r1[i]]`` (float32, elementwise: the same bits
    on every machine and thread count)."""
    out = np.empty((r0.shape[0], cols.shape[1]), dtype=np.float32)
    interpolate_rows_into(cols, r0, r1, fr, out)
    return out


@njit(cache=True, nogil=True)
def interpolate_rows_into(cols, r0, r1, fr, out):  # pragma: no cover - numba
    """:func:`interpolate_rows` written into ``out``."""
    n = r0.shape[0]
    m = cols.shape[1]
    one = np.float32(1.0)
    for i in range(n):
        f = fr[i]
        g = one - f
        a = cols[r0[i]]
        b = cols[r1[i]]
        for j in range(m):
            out[i, j] = a[j] * g + b[j] * f


@njit(cache=True, nogil=True)
def row_quartile_u8(img, k):  # pragma: no cover - numba
    """Order statistic ``k`` of each row of ``max(img, 0)`` by counting, for 8-bit data.

    Every value must be one of at most 256 distinct values in [0, 1], one per level
    ``round(255 v)`` (the image's own value of a level is the first one met): then ordering the
    levels orders the values, and the ``k``-th smallest value is the level where the row's
    cumulative count passes ``k``.  Returns ``(out, ok)``; ``ok`` False (``out`` undefined) when a
    value breaks that (not 8-bit data: sort instead).

    The readers' 8-bit images (every value ``level * float32(1 / 255)``) take
    :func:`_row_quartile_scaled`; any other data the general form.
    """
    out, ok, _ = row_quartile_scaled(img, k)
    return out, ok


@njit(cache=True, nogil=True)
def row_quartile_scaled(img, k):  # pragma: no cover - numba
    """:func:`row_quartile_u8` and whether the readers' form held (:func:`_row_quartile_scaled`):
    ``(out, ok, scaled)``.  ``scaled`` says that every positive value is ``level * float32(1 /
    255)`` for a level in 1 .. 255, so :func:`sonarmap.preprocess.normalise.on_8bit_grid` of the
    image is True (each such value times ``float32(255)`` lies within 2e-5 of its level)."""
    out = np.empty(img.shape[0], dtype=np.float32)
    if _row_quartile_scaled(img, k, out):
        return out, True, True
    out, ok = _row_quartile_levels(img, k)
    return out, ok, False


@njit(cache=True, nogil=True)
def _row_quartile_scaled(img, k, out):  # pragma: no cover - numba
    """:func:`row_quartile_u8` into ``out`` when every value of ``max(img, 0)`` is its level times
    ``float32(1 / 255)`` (then each level has one value and the result is the same); False (``out``
    partly written) when one is not.  The levels and that test come from one branch-free pass over
    each row (it vectorises), the first value of each level needs no table.  The levels are
    unsigned, as the scan's index: no negative-index wraparound code in the counting loops.  Each
    row's search starts from the previous row's level (counting the keys at most it on the way):
    a few steps instead of a scan from the row's lowest level."""
    n, m = img.shape
    keys = np.empty(m, dtype=np.uint32)
    count = np.zeros(256, dtype=np.int32)
    scale = np.float32(255.0)
    half = np.float32(0.5)
    step = np.float32(1.0 / 255.0)
    two = np.float32(2.0)
    t = np.uint32(0)  # the previous row's level: neighbouring rows' quartiles lie a few levels apart
    for i in range(n):
        row = img[i]
        good = True
        for j in range(m):
            v = row[j]
            v = min(v, two) if v > 0 else np.float32(0.0)  # (clamped: no overflowing level)
            key = np.uint32(v * scale + half)
            good &= (v <= 1.0) & (np.float32(key) * step == v)
            keys[j] = key
        if not good:
            return False
        c = 0  # the keys at most t
        for j in range(m):
            count[keys[j]] += 1
            c += keys[j] <= t
        # the k-th smallest key is the smallest t with more than k keys at most t: step down
        # while the level below t still has more, else up until t has
        if c > k:
            while t > 0 and c - count[t] > k:
                c -= count[t]
                t -= np.uint32(1)
        else:
            while c <= k:
                t += np.uint32(1)
                c += count[t]
        out[i] = np.float32(t) * step
        for j in range(m):
            count[keys[j]] = 0
    return True


@njit(cache=True, nogil=True)
def _row_quartile_levels(img, k):  # pragma: no cover - numba
    """:func:`row_quartile_u8` of any data: each level's value is the first one met, a value
    that breaks the one-value-per-level rule ends the count (``ok`` False)."""
    n, m = img.shape
    out = np.empty(n, dtype=np.float32)
    value = np.full(256, -1.0, dtype=np.float32)
    count = np.zeros(256, dtype=np.int32)
    keys = np.empty(m, dtype=np.int64)
    for i in range(n):
        lo = 255
        for j in range(m):
            v = img[i, j]
            if not v > 0:
                v = np.float32(0.0)
            if not v <= 1.0:
                return out, False
            key = int(v * np.float32(255.0) + np.float32(0.5))
            w = value[key]
            if w != v:
                if w >= 0:
                    return out, False
                value[key] = v
            count[key] += 1
            keys[j] = key
            lo = min(lo, key)
        c = 0
        for key in range(lo, 256):
            c += count[key]
            if c > k:
                out[i] = value[key]
                break
        for j in range(m):
            count[keys[j]] = 0
    return out, True


@njit(cache=True, nogil=True)
def median5(x):  # pragma: no cover - numba
    """``scipy.ndimage.median_filter(x, size=5, mode="nearest")`` of a 1-D float32 array without NaN
    (the middle one of the 5 values around each sample, edge samples repeated), by a branch-free
    min/max network: the middle of 5 is the middle of ``e``, the larger of the two pair minima
    and the smaller of the two pair maxima of ``a, b, c, d``."""
    n = x.size
    out = np.empty(n, dtype=np.float32)
    for i in range(n):
        a = x[min(max(i - 2, 0), n - 1)]
        b = x[min(max(i - 1, 0), n - 1)]
        c = x[i]
        d = x[min(i + 1, n - 1)]
        e = x[min(i + 2, n - 1)]
        f = max(min(a, b), min(c, d))
        g = min(max(a, b), max(c, d))
        out[i] = max(min(e, f), min(max(e, f), g))
    return out


@njit(cache=True, nogil=True, inline="always")
def _move_below(a, lo, hi, p, strict):  # pragma: no cover - numba
    """Branch-free partition pass: the values of ``a[lo:hi]`` below ``p`` (``strict``) or at most
    ``p`` to the front; returns ``lo`` + their count."""
    s = lo
    for i in range(lo, hi):
        t = a[i]
        a[i] = a[s]
        a[s] = t
        s += (t < p) if strict else (t <= p)
    return s


@njit(cache=True, nogil=True)
def select(a, n, k):  # pragma: no cover - numba
    """The ``k``-th smallest of ``a[:n]`` (no NaN), reordering ``a[:n]`` so that ``a[:k]`` holds
    values at most it (quickselect, pivots the median of 3 pseudo-random values - fixed ones
    degrade on the near-sorted, partitioned arrays of repeated selections -, values equal to the
    pivot split off)."""
    lo = 0
    hi = n
    state = np.uint64(0x9E3779B97F4A7C15)
    while hi - lo > 16:
        span = np.uint64(hi - lo)
        state = state * np.uint64(6364136223846793005) + np.uint64(1442695040888963407)
        x = a[lo + np.int64((state >> np.uint64(33)) % span)]
        state = state * np.uint64(6364136223846793005) + np.uint64(1442695040888963407)
        y = a[lo + np.int64((state >> np.uint64(33)) % span)]
        state = state * np.uint64(6364136223846793005) + np.uint64(1442695040888963407)
        z = a[lo + np.int64((state >> np.uint64(33)) % span)]
        p = max(min(x, y), min(max(x, y), z))
        s = _move_below(a, lo, hi, p, True)
        if k < s:
            hi = s
            continue
        e = _move_below(a, s, hi, p, False)
        if k < e:
            return p
        lo = e
    for i in range(lo + 1, hi):
        t = a[i]
        j = i - 1
        while j >= lo and a[j] > t:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = t
    return a[k]


#: :func:`median_inplace` finds the middle values of at least this many through a histogram.
MEDIAN_BUCKET_MIN = 256


@njit(cache=True, nogil=True)
def median_inplace(a, n):  # pragma: no cover - numba
    """``np.median(a[:n])`` of a float64 array without NaN (``n >= 1``; ``a[:n]`` is reordered):
    the middle value, or the mean ``(lo + hi) / 2`` of the two middle ones.  From
    :data:`MEDIAN_BUCKET_MIN` values on, the middle ones are found through a histogram
    (:func:`_bucket_middle`: a few passes that vectorise, against quickselect's data-dependent
    branches, 3x faster on 2000 values); the same values, so the same result."""
    if n >= MEDIAN_BUCKET_MIN:
        found, lo, hi = _bucket_middle(a, n)
        if found:
            return hi if n % 2 else (lo + hi) / 2.0
    hi = select(a, n, n // 2)
    if n % 2:
        return hi
    # a[:n // 2] now holds the n // 2 smallest values: the lower middle one is their maximum
    lo = a[0]
    for i in range(1, n // 2):
        lo = max(lo, a[i])
    return (lo + hi) / 2.0


@njit(cache=True, nogil=True)
def _bucket_middle(a, n):  # pragma: no cover - numba
    """``(found, lo, hi)``: the ``n // 2 - 1``-th (``lo``, when ``n`` is even) and ``n // 2``-th
    (``hi``) smallest of ``a[:n]`` (no NaN; ``a[:n]`` reordered), in ``a``'s dtype.  A histogram of
    256 equal buckets over ``[min, max]`` finds the bucket holding rank ``n // 2``, whose values are
    moved to the front and :func:`select`-ed; ``lo`` is the largest value below that rank, in the
    bucket or (when the rank is the bucket's first) in the buckets before it.  ``found`` False
    (nothing reordered) where all values are equal or their span is not finite."""
    found, mn, mx = _key_extremes(a, n)  # (vectorised; the float comparisons below otherwise)
    if not found:
        mn = a[0]
        mx = a[0]
        for t in range(1, n):
            v = a[t]
            mn = min(mn, v)
            mx = max(mx, v)
    span = np.float64(mx) - np.float64(mn)
    hist = np.empty((4, 256), dtype=np.int64)
    sc = (hist.shape[1] - 1e-3) / span if span > 0 else 0.0
    if not (span > 0 and np.isfinite(span) and np.isfinite(sc)):
        return False, mn, mx
    idx = np.empty(n, dtype=np.uint8)
    k = n // 2
    want, below = _rank_bucket(a, n, k, np.float64(mn), sc, hist, idx)
    lo = mn
    if n % 2 == 0 and k == below:  # the rank is the bucket's first: the value before it lies in a lower bucket
        for t in range(n):
            if idx[t] < want:
                lo = max(lo, a[t])
    hi = select(a, np.int64(_to_front(a, n, idx, want)), k - below)
    # a[:k - below] now holds the bucket's values before the rank
    for t in range(k - below):
        lo = max(lo, a[t])
    return True, lo, hi


#: Most rounds of :func:`smooth_log_level` (it stops earlier when the rows left out settle).
SMOOTH_ROUNDS = 10


@njit(cache=True, nogil=True)
def smooth_log_level(log_level, width, floor):  # pragma: no cover - numba
    """The robust smoothing of :func:`sonarmap.preprocess.normalise._row_level`: ``(smooth,
    above)``.  Rounds of: running means of ``keep`` and ``log_level * keep`` over ``width`` rows
    (scipy ``uniform_filter1d(mode="nearest")``) and their ratio where ``keep`` covers > 5 % of the
    window, linearly interpolated between such rows elsewhere (:func:`_fill_unsupported`); then
    the rows > 2.5 robust sigma above the curve and the contiguous rows > 0.5 sigma above it
    around them (:func:`_grow_above`; per row, sigma is at least ``floor``) are left out; until the rows left out no longer change (at most
    ``SMOOTH_ROUNDS`` rounds; ``len(log_level) > width``).  Finally the rows whose window holds a
    row left out take the quadratic through the kept rows on either side
    (:func:`_bridge_left_out`)."""
    n = log_level.size
    keep = np.ones(n)
    smooth = log_level.copy()
    above = np.zeros(n, dtype=np.bool_)
    den = np.empty(n)
    num = np.empty(n)
    work = np.empty(n)
    resid = np.empty(n)
    for _ in range(SMOOTH_ROUNDS):
        for i in range(n):
            work[i] = log_level[i] * keep[i]
        # _running_mean of keep and of work: the two sums' chains of additions advance together,
        # their divisions in loops of their own (which vectorise), branch-free
        _running_sums2(keep, work, den, num, width)
        for i in range(n):
            den[i] = den[i] / width
            num[i] = num[i] / width
        for i in range(n):
            v = num[i] / max(den[i], 1e-12)
            smooth[i] = v if den[i] > 0.05 else smooth[i]
        _fill_unsupported(smooth, den)
        c = 0
        for i in range(n):
            resid[i] = log_level[i] - smooth[i]
            if keep[i] > 0:
                work[c] = abs(resid[i])
                c += 1
        # (np.int64: a counter that starts at a literal 0 would also compile median_inplace, and the
        # kernels it calls, for a Literal[int](0) argument)
        sigma = 1.4826 * median_inplace(work, np.int64(c)) if c > 0 else 0.0
        if not _grow_above(resid, sigma, floor, above, keep):
            break
    _bridge_left_out(log_level, keep, width, smooth, den, num, work)
    return smooth, above


@njit(cache=True, nogil=True)
def _bridge_left_out(y, keep, width, smooth, count, num, work):  # pragma: no cover - numba
    """Lower ``smooth`` on every stretch of rows whose ``width``-row window holds a row left
    out (``keep`` = 0) to the least-squares quadratic through the kept rows of ``y`` within
    ``2 width`` rows of the stretch on either side, where that lies below it - but not below the
    lower of the curve's values just beside the stretch (in place; ``count``, ``num``, ``work``
    are scratch of ``y``'s size).  A stretch with fewer than ``width // 2`` kept rows on either
    side (the window's ends, the ring-down) keeps its curve.

    The running means beside a left-out surface are one-sided means half a window away on a
    level that falls with range, and the straight line :func:`_fill_unsupported` draws between
    them is a chord of a convex curve: above it, in front of and under the surface (simulated
    ARIS 3000 seafloor: +1.6-3 %).  The quadratic through the kept rows on both sides follows the
    curve: over rows 500-760 of that seafloor the level lies within -1.9 / +0.7 % of the level
    estimated on the same seed's empty scene (seeds 0-2, both noise levels).  The
    bounds keep a quadratic through an uneven neighbourhood from raising the level (a palettised
    DIDSON frame's ring-down of 8 levels beside a background of 1-2: a quadratic peaking at 16) or
    dipping below the background on either side."""
    n = y.size
    for i in range(n):
        work[i] = y[i] * keep[i]
    _running_sums2(keep, work, count, num, width)
    i = 0
    while i < n:
        if count[i] >= width:  # (sums of 0/1 values: exact)
            i += 1
            continue
        a = i
        while i < n and count[i] < width:
            i += 1
        b = i
        lo = max(a - 2 * width, 0)
        hi = min(b + 2 * width, n)
        n_left = 0.0
        for k in range(lo, a):
            n_left += keep[k]
        n_right = 0.0
        for k in range(b, hi):
            n_right += keep[k]
        if n_left < width // 2 or n_right < width // 2:
            continue
        # the quadratic in t = (k - centre) / (hi - lo), its normal equations' sums
        c0 = 0.5 * (a + b - 1)
        sc = 1.0 / (hi - lo)
        s0 = s1 = s2 = s3 = s4 = 0.0
        r0 = r1 = r2 = 0.0
        for k in range(lo, hi):
            if keep[k] > 0 and (k < a or k >= b):
                t = (k - c0) * sc
                t2 = t * t
                s0 += 1.0
                s1 += t
                s2 += t2
                s3 += t2 * t
                s4 += t2 * t2
                r0 += y[k]
                r1 += t * y[k]
                r2 += t2 * y[k]
        # Cramer's rule on [[s0 s1 s2] [s1 s2 s3] [s2 s3 s4]] (q0, q1, q2) = (r0, r1, r2)
        det = s0 * (s2 * s4 - s3 * s3) - s1 * (s1 * s4 - s3 * s2) + s2 * (s1 * s3 - s2 * s2)
        if not abs(det) > 1e-12:
            continue
        q0 = (r0 * (s2 * s4 - s3 * s3) - s1 * (r1 * s4 - s3 * r2) + s2 * (r1 * s3 - s2 * r2)) / det
        q1 = (s0 * (r1 * s4 - r2 * s3) - r0 * (s1 * s4 - s3 * s2) + s2 * (s1 * r2 - r1 * s2)) / det
        q2 = (s0 * (s2 * r2 - s3 * r1) - s1 * (s1 * r2 - s2 * r1) + r0 * (s1 * s3 - s2 * s2)) / det
        # never above the interpolated curve, never below the lower of its values beside the stretch
        low = min(smooth[a - 1], smooth[b])
        for k in range(a, b):
            t = (k - c0) * sc
            smooth[k] = min(max(q0 + q1 * t + q2 * t * t, low), smooth[k])


@njit(cache=True, nogil=True, inline="always")
def _running_sums2(a, b, sa, sb, size):  # pragma: no cover - numba
    """The running sums of :func:`_running_mean` (before its division by ``size``) of ``a`` and
    ``b`` (float64, one length) into ``sa`` and ``sb``, the two sums advanced together (the same
    additions per array)."""
    n = a.shape[0]
    h = size // 2
    s = 0.0
    t = 0.0
    for k in range(-h, size - h):
        c = min(max(k, 0), n - 1)
        s += a[c]
        t += b[c]
    for i in range(n):
        sa[i] = s
        sb[i] = t
        p = min(max(i - h + size, 0), n - 1)
        q = min(max(i - h, 0), n - 1)
        s += a[p] - a[q]
        t += b[p] - b[q]


@njit(cache=True, nogil=True)
def _fill_unsupported(smooth, den):  # pragma: no cover - numba
    """``smooth`` over the rows whose window holds <= 5 % kept rows (``den``), linearly
    interpolated between the nearest rows on either side that hold more (the nearest one's value
    towards an end; unchanged when no row holds more)."""
    n = smooth.size
    last = -1
    i = 0
    while i < n:
        if den[i] > 0.05:
            last = i
            i += 1
            continue
        j = i
        while j < n and not den[j] > 0.05:
            j += 1
        if last < 0 and j >= n:
            return
        for k in range(i, j):
            if last < 0:
                smooth[k] = smooth[j]
            elif j >= n:
                smooth[k] = smooth[last]
            else:
                smooth[k] = smooth[last] + (smooth[j] - smooth[last]) * (k - last) / (j - last)
        i = j


@njit(cache=True, nogil=True)
def _grow_above(resid, sigma, floor, above, keep):  # pragma: no cover - numba
    """Rows of residual ``resid`` > 2.5 ``s`` and the contiguous rows of residual > 0.5 ``s`` on
    either side of them (a surface's echo is left out whole, its flanks too), ``s`` the row's
    ``max(sigma, floor)``, into ``above`` (``keep`` = 0 there, 1 elsewhere); whether ``above``
    changed."""
    n = resid.size
    changed = False
    new = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if resid[i] > 2.5 * max(sigma, floor[i]):
            new[i] = True
    for i in range(1, n):
        if not new[i] and new[i - 1] and resid[i] > 0.5 * max(sigma, floor[i]):
            new[i] = True
    for i in range(n - 2, -1, -1):
        if not new[i] and new[i + 1] and resid[i] > 0.5 * max(sigma, floor[i]):
            new[i] = True
    for i in range(n):
        if new[i] != above[i]:
            changed = True
        above[i] = new[i]
        keep[i] = 0.0 if new[i] else 1.0
    return changed


@njit(cache=True, nogil=True)
def level_tail(smooth, level, above, max_rise, rise):  # pragma: no cover - numba
    """The end of :func:`sonarmap.preprocess.normalise._row_level` (float64 ``smooth = exp(...)``
    and ``level``): ``level`` over the leading rows of ``above``, float32, then (``rise``) at most
    ``max_rise`` times its running minimum - numpy's ``np.minimum(out, max_rise *
    np.minimum.accumulate(out))`` as float32 (``max_rise`` float32 or float64: the product's
    precision)."""
    n = smooth.size
    out = np.empty(n, dtype=np.float32)
    lead = 0
    while lead < n and above[lead]:
        lead += 1
    for i in range(n):
        out[i] = level[i] if i < lead else smooth[i]
    if rise and n > 0:
        low = out[0]
        for i in range(n):
            v = out[i]
            low = min(low, v)
            out[i] = min(v, max_rise * low)
    return out


#: Buckets of :func:`block_quartiles`' histogram (the bucket holding the wanted rank is then
#: selected from: ~1/64 of a block).
QUARTILE_BUCKETS = 64


@njit(cache=True, nogil=True, error_model="numpy")
def block_quartiles(img, level, nr, nc, br, bc, k, work, hist):  # pragma: no cover - numba
    """Per block of ``br x bc`` of ``img / level[:, None]`` (float32, as numpy divides them), its
    ``k``-th smallest value (0-based; NaN sorts last, as ``np.partition``): ``(nr nc,)`` float32,
    block ``(a, b)`` at ``a * nc + b``.  ``work`` (float32, ``(nc, br bc)``) and ``hist`` (int64,
    ``(4, QUARTILE_BUCKETS)``) are scratch.  The image is read once, row by row (a block row's
    ``nc`` blocks filled together, a block's values in row-major order: a loop without branches,
    which vectorises); each block's NaN are then dropped and its value selected exactly
    (:func:`_bucket_select`).  A zero level divides as numpy does (``x / 0 = inf``, ``0 / 0 =
    NaN``)."""
    out = np.empty(nr * nc, np.float32)
    idx = np.empty(br * bc, np.uint8)
    for a in range(nr):
        for i in range(br):
            r = a * br + i
            lv = level[r]
            base = i * bc
            for b in range(nc):
                row = work[b]
                src = img[r, b * bc: (b + 1) * bc]
                for j in range(bc):
                    row[base + j] = np.float32(src[j] / lv)
        for b in range(nc):
            n, mn, mx = _without_nan(work[b], br * bc)
            out[a * nc + b] = _bucket_select(work[b], n, k, mn, mx, hist, idx)
    return out


@njit(cache=True, nogil=True)
def _without_nan(a, n):  # pragma: no cover - numba
    """``(count, min, max)`` of the values of ``a[:n]`` (float32, C-contiguous) that are not NaN,
    those moved to the front in their order (``a`` untouched when none is NaN); ``(0, inf, -inf)``
    when all are.  Without NaN and ``-0.0`` (:func:`_key_extremes`) the extremes come from one
    integer pass that vectorises; else from the float comparisons."""
    found, mn, mx = _key_extremes(a, n)
    if found:
        return n, mn, mx
    mn = np.float32(np.inf)
    mx = np.float32(-np.inf)
    bad = 0
    for t in range(n):
        v = a[t]
        if np.isnan(v):
            bad += 1
        else:
            mn = min(mn, v)
            mx = max(mx, v)
    if bad:
        w = 0
        for t in range(n):
            v = a[t]
            if not np.isnan(v):
                a[w] = v
                w += 1
    return n - bad, mn, mx


def _key_extremes(a, n):  # pragma: no cover - numba (typed by its overload)
    """``(found, min, max)`` of ``a[:n]`` (float32 or float64, C-contiguous, ``n >= 1``) through the
    values' bits as sortable integers (``bits ^ 0x7ff...f`` for negative values: the integers' order
    is the floats'), in one branch-free pass (a float min/max reduction does not vectorise without
    fast-math); ``found`` False when a value is NaN or ``-0.0`` (``-0.0 == 0.0`` but their keys
    differ), ``n < 1`` or ``a`` is not C-contiguous.  The same extremes, in ``a``'s dtype, as
    ``min``/``max`` over the floats."""
    raise NotImplementedError("numba only")


@overload(_key_extremes, inline="always")
def _key_extremes_typed(a, n):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    """:func:`_key_extremes` for ``a``'s dtype: the integers of its width, sign bit ``top``."""
    if not isinstance(a, types.Array) or a.layout != "C" or a.dtype not in (types.float32, types.float64):
        return lambda a, n: (False, a[0], a[0])
    wide = a.dtype == types.float64
    ity, fty = (np.int64, np.float64) if wide else (np.int32, np.float32)
    shift = 63 if wide else 31
    mag = (1 << shift) - 1           # every bit but the sign
    top = -(1 << shift)              # the sign bit alone: -0.0
    inf = 0x7FF0000000000000 if wide else 0x7F800000

    def impl(a, n):  # type: ignore[no-untyped-def]
        bits = a[:n].view(ity)
        lo = np.int64(mag)
        hi = np.int64(top)
        odd = 0
        for t in range(n):
            u = np.int64(bits[t])
            key = u ^ ((u >> shift) & mag)
            lo = min(lo, key)
            hi = max(hi, key)
            odd += ((u & mag) > inf) | (u == top)  # NaN or -0.0
        out = np.empty(2, ity)
        out[0] = lo ^ ((lo >> shift) & mag)
        out[1] = hi ^ ((hi >> shift) & mag)
        f = out.view(fty)
        return odd == 0 and n > 0, f[0], f[1]

    return impl


@njit(cache=True, nogil=True)
def _bucket_select(a, n, k, mn, mx, hist, idx):  # pragma: no cover - numba
    """The ``k``-th smallest of ``a[:n]`` (no NaN; ``mn``, ``mx`` its extremes; NaN when ``k >=
    n``; ``a`` reordered): a histogram of ``hist.shape[1]`` equal buckets over ``[mn, mx]`` finds
    the bucket holding rank ``k``, whose values are moved to the front and :func:`select`-ed.
    Exact: each value's bucket is computed once (into ``idx``, uint8, at least ``n`` long).  The
    histogram is counted in 4 interleaved parts (rows of ``hist``): runs of one bucket (a
    background's values crowd a few) do not serialise.  Non-finite extremes: :func:`select` on all."""
    if k >= n:
        return np.float32(np.nan)
    if mx == mn:
        return mn
    nb = hist.shape[1]
    sc = (nb - 1e-3) / (np.float64(mx) - np.float64(mn))
    if not (np.isfinite(mn) and np.isfinite(mx) and np.isfinite(sc)):
        return select(a, n, k)
    want, below = _rank_bucket(a, n, k, np.float64(mn), sc, hist, idx)
    return select(a, np.int64(_to_front(a, n, idx, want)), k - below)


@njit(cache=True, nogil=True, inline="always")
def _rank_bucket(a, n, k, mn, sc, hist, idx):  # pragma: no cover - numba
    """``(bucket, below)``: the bucket ``int((a[t] - mn) sc)`` (float64; ``idx[t]``, uint8) holding
    rank ``k`` of ``a[:n]`` and the number of values in the buckets before it, from the histogram
    ``hist`` (int64, ``(4, n_buckets)``, overwritten) of the buckets."""
    for t in range(n):
        idx[t] = np.uint8(int((np.float64(a[t]) - mn) * sc))
    hist[:, :] = 0
    add_partial_counts(idx, n, hist)
    below = 0
    bucket = 0
    while True:
        count = hist[0, bucket] + hist[1, bucket] + hist[2, bucket] + hist[3, bucket]
        if below + count > k:
            break
        below += count
        bucket += 1
    return np.uint8(bucket), below


@njit(cache=True, nogil=True, inline="always")
def _to_front(a, n, idx, want):  # pragma: no cover - numba
    """Move the values of ``a[:n]`` whose ``idx`` is ``want`` to the front, in order; their count."""
    w = 0
    for t in range(n):
        v = a[t]
        if idx[t] == want:
            a[w] = v
            w += 1
    return w


@njit(cache=True, nogil=True)
def rows_ranked_at_most(z, t, k):  # pragma: no cover - numba
    """The rows of ``z`` (ascending) holding more than ``k`` values at most ``t``: those whose
    ``k``-th smallest value (0-based; NaN sorts last) is at most ``t``.  One pass that counts
    (vectorised along the rows)."""
    n, m = z.shape
    out = np.empty(n, dtype=np.intp)
    c = 0
    for i in range(n):
        cnt = 0
        for j in range(m):
            cnt += z[i, j] <= t
        out[c] = i
        c += cnt > k
    return out[:c]


@njit(cache=True, nogil=True)
def background_rows(q25, q50, n_rows):  # pragma: no cover - numba
    """``(median(q50[rows]), median((q50 - q25)[rows]))`` over ``rows``, the first ``n_rows`` of
    ``np.argsort(q50, kind="stable")``: every row below the ``n_rows``-th smallest ``q50`` and the
    first rows equal to it.  NaN-free float64 input."""
    n = q50.size
    work = q50.copy()
    v = select(work, n, n_rows - 1)
    below = 0
    for i in range(n):
        below += q50[i] < v
    ties = n_rows - below
    spread = np.empty(n_rows)
    c = 0
    for i in range(n):
        if q50[i] < v or (q50[i] == v and ties > 0):
            if q50[i] == v:
                ties -= 1
            work[c] = q50[i]
            spread[c] = q50[i] - q25[i]
            c += 1
    return median_inplace(work, n_rows), median_inplace(spread, n_rows)


@njit(cache=True, nogil=True)
def excess_top(z, t, gain, scale, levels):  # pragma: no cover - numba
    """``u = min(gain * max(z - t, 0), 1)`` as float32, the number of its values at 1, and whether
    every value is finite; ``levels`` (uint8, ``z``'s shape) receives ``rint(u * scale)``, float32
    ``scale <= 255``: the quantisation levels of ``u`` (:func:`sonarmap.stats.mixture.quantize`
    with ``scale = L - 1``, round binning, the same float32 arithmetic), undefined where ``u`` is
    NaN.  ``z`` C-contiguous: one loop over its pixels, which vectorises (per row, a short row -
    48 beams - did not); the levels cost no pass over ``u`` of their own."""
    out = np.empty(z.shape, dtype=np.float32)
    src = z.ravel()
    dst = out.ravel()
    lev = levels.ravel()
    zero = np.float32(0.0)
    one = np.float32(1.0)
    top = 0
    bad = False
    for k in range(src.size):
        e = (src[k] - t) * gain
        u = zero if e <= zero else (one if e > one else e)
        dst[k] = u
        top += u >= one
        bad |= u != u
        lev[k] = np.uint8(np.rint(u * scale))
    return out, top, not bad


@njit(cache=True, nogil=True)
def percentiles_linear(x, q):  # pragma: no cover - numba
    """``np.percentile(x, 100 q)`` (method "linear") of a 1-D array without NaN, ``n >= 2`` values,
    ``0 <= q < 1``: numpy's arithmetic - the virtual index ``(n - 1) q``, its floor ``i`` and
    fraction ``g``, the difference ``d = x[i + 1] - x[i]`` in the input's precision, then
    ``x[i] + d g`` (``g < 0.5``) or ``x[i + 1] - d (1 - g)`` in float64."""
    n = x.size
    a = x.copy()
    out = np.empty(q.size)
    for t in range(q.size):
        v = (n - 1) * q[t]
        i = int(np.floor(v))
        g = v - i
        lo = select(a, n, i)
        hi = a[i + 1]
        for k in range(i + 2, n):
            hi = min(hi, a[k])
        d = hi - lo
        out[t] = hi - d * (1.0 - g) if g >= 0.5 else lo + d * g
    return out


@njit(cache=True, nogil=True)
def finite_and_zeros(img, zero):  # pragma: no cover - numba
    """``(np.all(np.isfinite(img)), np.count_nonzero(img <= zero))`` of a C-contiguous float32 image
    in one pass (``zero`` float32) over its pixels as one array (vectorised; short rows were not)."""
    flat = img.ravel()
    finite = True
    zeros = 0
    for k in range(flat.size):
        v = flat[k]
        finite &= np.isfinite(v)
        zeros += v <= zero
    return finite, zeros


@njit(cache=True, nogil=True)
def on_255_grid(flat, step):  # pragma: no cover - numba
    """``np.all(np.abs(s - np.rint(s)) < 1e-3)`` with ``s = pos * np.float32(255)`` over the positive
    values ``pos`` of ``flat[::step]`` (float32 or float64, the same arithmetic as numpy's), stopping
    after the first block of 256 samples with a value off the grid (branch-free within a block:
    zeros and positives alternate unpredictably in thresholded images)."""
    scale = np.float32(255.0)
    n = flat.size
    for k0 in range(0, n, 256 * step):
        miss = False
        for k in range(k0, min(k0 + 256 * step, n), step):
            v = flat[k]
            s = v * scale
            miss |= (v > 0) & (not abs(s - np.rint(s)) < 1e-3)
        if miss:
            return False
    return True


@njit(cache=True, nogil=True)
def clip_negative(out):  # pragma: no cover - numba
    """``np.maximum(out, 0, out=out)`` on a C-contiguous float32 image, bit for bit (NaN kept,
    ``-0.0`` becomes ``0.0`` as with numpy's maximum); branch-free, so it vectorises."""
    flat = out.reshape(-1)
    zero = np.float32(0.0)
    for i in range(flat.size):
        x = flat[i]
        flat[i] = x if (x > zero) | (x != x) else zero


@njit(cache=True, nogil=True)
def clip_rescale(out, top, subtract_min):  # pragma: no cover - numba
    """:func:`clip_negative`, then the pre-processing's normalisation of a C-contiguous float32
    image, bit for bit: ``out -= out.min()`` with ``subtract_min``, then ``out *= float32(top /
    out.max())`` when that maximum is positive.

    After the clipping every value is ``+0.0``, positive or NaN, so their bit patterns read as
    unsigned integers order them (NaN above ``+inf``): the minimum and maximum are integer
    reductions, which vectorise (a float one does not).  Returns False, having only clipped, when
    a value is NaN (the caller takes numpy's way: the NaN propagates through the minimum).
    """
    flat = out.reshape(-1)
    bits = flat.view(np.uint32)
    zero = np.float32(0.0)
    n = flat.size
    for i in range(n):
        x = flat[i]
        flat[i] = x if (x > zero) | (x != x) else zero
    inf = np.uint32(0x7F800000)
    lo = np.uint32(0xFFFFFFFF)
    hi = np.uint32(0)
    for i in range(n):
        u = bits[i]
        lo = min(lo, u)
        hi = max(hi, u)
    if hi > inf:
        return False
    if subtract_min:
        word = np.empty(1, dtype=np.uint32)
        word[0] = lo
        m = word.view(np.float32)[0]
        for i in range(n):
            flat[i] = flat[i] - m
        hi = np.uint32(0)
        for i in range(n):
            hi = max(hi, bits[i])
    if hi > inf or hi == 0:  # the maximum is NaN (+inf - +inf) or zero: no scaling
        return True
    word = np.empty(1, dtype=np.uint32)
    word[0] = hi
    s = np.float32(top / np.float64(word.view(np.float32)[0]))
    for i in range(n):
        flat[i] = flat[i] * s
    return True


@njit(cache=True, nogil=True)
def _first_rows(struct):  # pragma: no cover - numba
    """Per column of ``struct`` (uint8) the row of its first non-zero pixel (the row count where none)."""
    n, m = struct.shape
    first = np.full(m, n, np.int64)
    left = m
    for i in range(n):
        if left == 0:
            break
        for j in range(m):
            if first[j] == n and struct[i, j] != 0:
                first[j] = i
                left -= 1
    return first


@njit(cache=True, nogil=True)
def _water_column_median(img, first, margin, i, buf):  # pragma: no cover - numba
    """The median of row ``i``'s water-column pixels (``buf``: scratch of the row's width)."""
    k = 0
    for j in range(img.shape[1]):
        if i < first[j] - margin:
            buf[k] = np.float64(img[i, j])
            k += 1
    return median_inplace(buf, np.int64(k)) if k > 0 else 0.0


@njit(cache=True, nogil=True)
def crosstalk_rows(img, struct, margin, front, need, z, grow):  # pragma: no cover - numba
    """Per row of ``img`` the crosstalk level of :func:`sonarmap.preprocess.crosstalk.crosstalk_by_row`
    (0 where none): the excess of the median of its water-column pixels - those more than
    ``margin`` rows in front of their column's first non-zero ``struct`` (uint8) pixel - over the
    ping's typical one, where it exceeds ``z`` standard errors, on the rows holding a structure
    pixel in some column (crosstalk lies at an echo's range); rows with fewer than ``need`` such
    pixels, or more than ``front`` rows in front of the first structure pixel, get none.
    The medians are taken only of the rows whose mean is significant by the same test (a row lit
    across the fan raises both; the means take one pass that vectorises) and of 15 rows spread
    over the others for the typical median.  A band found so grows, row by row in both
    directions, into the lit rows beside it that have fewer than ``need`` but at least ``grow``
    (<= ``need``) water-column pixels, while they pass the same tests: a band is contiguous in
    range, and where a surface fills more of the fan beside the band fewer beams see it."""
    n, m = img.shape
    out = np.zeros(n)
    first = _first_rows(struct)
    lo = n
    hi = 0
    for j in range(m):
        lo = min(lo, first[j])
        hi = max(hi, first[j] - margin)
    lo = max(lo - front, 0)
    hi = min(hi, n)
    if hi - lo < 8:
        return out
    mean = np.zeros(hi - lo)
    cnt = np.zeros(hi - lo, np.int64)
    few = np.zeros(hi - lo, np.int64)
    s = 0.0
    s2 = 0.0
    lit = np.zeros(hi - lo, np.bool_)
    for i in range(lo, hi):
        a = 0.0
        b = 0.0
        k = 0
        e = 0
        for j in range(m):
            w = i < first[j] - margin
            v = np.float64(img[i, j]) if w else 0.0
            a += v
            b += v * v
            k += w
            e += struct[i, j] != 0
        lit[i - lo] = e > 0
        if k >= need:
            mean[i - lo] = a / k
            cnt[i - lo] = k
            s += a
            s2 += b
        elif k >= grow:
            mean[i - lo] = a / k
            few[i - lo] = k
    ok = np.flatnonzero(cnt)
    if ok.size < 8:
        return out
    total = np.float64(cnt.sum())
    sd = np.sqrt(max(s2 / total - (s / total) ** 2, 0.0))
    means = mean[ok].copy()
    base_mean = median_inplace(means, means.size)
    buf = np.empty(m)
    # the typical median: of 15 rows spread over the rows with an estimate
    typical = np.empty(min(ok.size, 15))
    for t in range(typical.size):
        typical[t] = _water_column_median(img, first, margin, lo + ok[(t * ok.size) // typical.size], buf)
    base = median_inplace(typical, typical.size)
    for t in range(ok.size):
        r = ok[t]
        out[lo + r] = _crosstalk_excess(img, first, margin, lo, r, cnt[r], mean, lit, sd, base_mean, base, z, buf)
    # the bands grow into their neighbouring rows with fewer water-column pixels: a sweep each way,
    # a row tested where the row before it (in the sweep) carries crosstalk
    for d in (1, -1):
        for t in range(1, hi - lo):
            q = t if d == 1 else hi - lo - 1 - t
            if few[q] > 0 and out[lo + q] == 0 and out[lo + q - d] > 0:
                out[lo + q] = _crosstalk_excess(img, first, margin, lo, q, few[q], mean, lit, sd, base_mean, base,
                                                z, buf)
    return out


@njit(cache=True, nogil=True)
def _crosstalk_excess(img, first, margin, lo, r, k, mean, lit, sd, base_mean, base, z, buf):  # pragma: no cover
    """Row ``lo + r``'s crosstalk level of :func:`crosstalk_rows` from its ``k`` water-column
    pixels (mean ``mean[r]``): its median's excess over ``base`` where the mean and the median
    both pass the ``z`` standard-error tests on a lit row, else 0."""
    se = sd / np.sqrt(np.float64(k))
    if lit[r] and mean[r] - base_mean > z * se:
        x = _water_column_median(img, first, margin, lo + r, buf) - base
        if x > z * 1.2533 * se:  # (a median's standard error: sqrt(pi / 2) x the mean's)
            return x
    return 0.0
