"""Numba kernels of the range stage (private; see :mod:`sonarmap.ranges` (components, first runs,
leading edges), :mod:`sonarmap.ranges.echoes` and :mod:`sonarmap.ranges.tracking`).

Images are ``(n_bins, n_beams)``; an echo is identified by its index in the flat per-echo arrays,
sorted by beam and then by range.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _column_counts(mask, r0, r1):  # pragma: no cover - numba
    """``first``: the true pixels of column ``j`` of the C-contiguous ``mask`` on rows ``r0 .. r1 -
    1`` (within the image) number ``first[j + 1] - first[j]`` (one branch-free pass; ``first[-1]``
    is their total)."""
    n, m = mask.shape
    flat = mask.reshape(n * m).view(np.uint8)
    # (counted per column into their own array, row by row through a slice: this loop vectorises,
    # the one adding into ``first[j + 1]`` did not - Oculus masks 30 -> 5 us)
    count = np.zeros(m, np.int64)
    for i in range(r0, r1):
        row = flat[i * m:(i + 1) * m]
        for j in range(m):
            count[j] += row[j] != 0
    first = np.zeros(m + 1, np.int64)
    for j in range(m):
        first[j + 1] = first[j] + count[j]
    return first


@njit(cache=True, nogil=True)
def _column_pixels(mask, img, code, lut, boost, boost_min, r0, r1, first):  # pragma: no cover - numba
    """``(rows, pix)``: the true pixels of column ``j`` of the C-contiguous ``mask``, all on rows
    ``r0 .. r1 - 1`` (within the image), lie at rows ``rows[first[j] : first[j + 1]]`` (ascending;
    ``first`` of :func:`_column_counts`); ``pix`` holds their image values (float64, exact) and
    evidence (see :func:`_pixel_evidence`) side by side.  One pass over those rows, which skips 8
    empty pixels at a time (the image read along its rows, not down its columns).  (Values and
    evidence in separate arrays made the fill 10x slower: the writes of the 3 arrays at one index
    conflict in the cache.)"""
    n, m = mask.shape
    flat = mask.reshape(n * m).view(np.uint8)
    rows = np.empty(first[m], np.int64)
    pix = np.empty((first[m], 2), np.float64)
    has_boost = boost.shape[0] == n
    fill = first[:m].copy()
    by_words = m % 8 == 0
    words = flat.view(np.uint64) if by_words else np.zeros(0, np.uint64)
    for i in range(r0, r1):
        base = i * m
        if by_words:
            for w in range(m // 8):
                if words[(base >> 3) + w] != 0:
                    for j in range(8 * w, 8 * w + 8):
                        if flat[base + j]:
                            t = fill[j]
                            rows[t] = i
                            pix[t, 0] = img[i, j]
                            pix[t, 1] = _pixel_evidence(code, lut, boost, has_boost, boost_min, i, j)
                            fill[j] += 1
        else:
            for j in range(m):
                if flat[base + j]:
                    t = fill[j]
                    rows[t] = i
                    pix[t, 0] = img[i, j]
                    pix[t, 1] = _pixel_evidence(code, lut, boost, has_boost, boost_min, i, j)
                    fill[j] += 1
    return rows, pix


@njit(cache=True, nogil=True, inline="always")
def _pixel_evidence(code, lut, boost, has_boost, boost_min, i, j):  # pragma: no cover - numba
    """A structure pixel's evidence: ``lut[code[i, j]]``, at least ``boost_min`` where ``boost``
    is set."""
    v = lut[code[i, j]]
    if has_boost and boost[i, j] and v < boost_min:
        v = boost_min
    return v


@njit(cache=True, nogil=True)
def find_echoes(mask, img, code, lut, boost, boost_min, max_gap, fraction, peak_rel, back, forward, r0,
                r1):  # pragma: no cover - numba
    """Echoes along every beam (see :func:`sonarmap.ranges.echoes.find_echoes`), whose structure
    pixels (``mask``) all lie on rows ``r0 .. r1 - 1``.

    Returns per echo: beam, start, stop (exclusive, structure pixels), peak bin, peak value,
    edge position (fractional bin index of the ``fraction`` crossing), edge slope (value per
    bin at the crossing), evidence (sum over the echo's structure pixels of ``lut[code[i, j]]``,
    at least ``boost_min`` where ``boost`` (shape (1, 1): nowhere) is set) and its number of
    structure pixels.
    """
    # the structure pixels of every column in range order, from one pass over the rows (a scan
    # down each column of the mostly empty mask was most of the kernel's time); a mask filling
    # more than half its rows (4096 x 512 simulated hull: 70 %) is walked along its rows instead,
    # without gathering the pixels (2.8 -> 1.5 ms; Oculus' masks fill ~35 %)
    n, m = mask.shape
    r0 = max(r0, 0)
    r1 = max(min(r1, n), r0)
    col_first = _column_counts(mask, r0, r1)
    if boost.shape[0] != n and 2 * col_first[m] > (r1 - r0) * m:
        # more than half the pixels of the rows are structure: one pass along the rows
        return _echoes_by_rows(mask, img, code, lut, max_gap, fraction, peak_rel, back, forward, r0, r1)
    rows, pix = _column_pixels(mask, img, code, lut, boost, boost_min, r0, r1, col_first)
    return _echoes_of_columns(img, max_gap, fraction, peak_rel, back, forward, np.arange(mask.shape[1]), col_first,
                              rows, pix)


@njit(cache=True, nogil=True)
def find_echoes_in(mask, img, code, lut, boost, boost_min, max_gap, fraction, peak_rel, back, forward, cols, r0,
                   r1):  # pragma: no cover - numba
    """:func:`find_echoes` on the columns ``cols`` only (ascending), whose true pixels of ``mask``
    lie on rows ``r0 .. r1 - 1``: the echoes of those beams, the same as :func:`find_echoes` gives
    them (each beam's echoes depend on its column alone)."""
    r0 = max(r0, 0)
    r1 = min(r1, mask.shape[0])
    # the pixels gathered along the rows, each row read once for all the columns (walks down the
    # columns of a tall image missed the cache at every row: 4096 x 512 pings ~370 -> ~290 us)
    nc = cols.size
    count = np.zeros(nc, np.int64)
    for i in range(r0, r1):
        row = mask[i]
        for c in range(nc):
            count[c] += row[cols[c]]
    col_first = np.zeros(nc + 1, np.int64)
    for c in range(nc):
        col_first[c + 1] = col_first[c] + count[c]
    rows = np.empty(col_first[nc], np.int64)
    pix = np.empty((col_first[nc], 2), np.float64)
    has_boost = boost.shape[0] == mask.shape[0]
    fill = col_first[:nc].copy()
    for i in range(r0, r1):
        row = mask[i]
        for c in range(nc):
            j = cols[c]
            if row[j]:
                t = fill[c]
                rows[t] = i
                pix[t, 0] = img[i, j]
                pix[t, 1] = _pixel_evidence(code, lut, boost, has_boost, boost_min, i, j)
                fill[c] = t + 1
    return _echoes_of_columns(img, max_gap, fraction, peak_rel, back, forward, cols, col_first, rows, pix)


@njit(cache=True, nogil=True, inline="always")
def _edge_of_peak(img, j, s, p, fraction, back, forward):  # pragma: no cover - numba
    """``(peak value, edge position, edge slope)`` of the echo of column ``j`` starting at bin ``s``
    whose first peak is at bin ``p`` (see :func:`find_echoes`)."""
    n = img.shape[0]
    # the peak's height, refined by a parabola through its neighbours (a sampled peak is
    # lower than the echo's: the half-peak level would move with the sampling phase)
    pv = np.float64(img[p, j])
    if 0 < p < n - 1 and img[p - 1, j] < pv and img[p + 1, j] < pv:
        den = img[p - 1, j] - 2.0 * pv + img[p + 1, j]
        if den < 0.0:
            pv = pv - 0.125 * (img[p - 1, j] - img[p + 1, j]) ** 2 / den
    level = fraction * pv
    # the leading edge, at most `back` bins in front of the echo
    lo = max(s - back, 0)
    if forward:
        # the first bin from in front of the echo that reaches the level
        q = lo
        while q < p and img[q, j] < level:
            q += 1
    else:
        # walk back from the peak while the image stays at or above the level
        q = p
        while q > lo and img[q - 1, j] >= level:
            q -= 1
    if q > 0 and img[q - 1, j] < level and img[q, j] > img[q - 1, j]:
        d = img[q, j] - img[q - 1, j]
        return pv, (q - 1) + (level - img[q - 1, j]) / d, np.float64(d)
    return pv, float(q), np.float64(img[p, j] if p == q else (img[p, j] - img[q, j]) / (p - q))


@njit(cache=True, nogil=True)
def _echoes_by_rows(mask, img, code, lut, max_gap, fraction, peak_rel, back, forward, r0,
                    r1):  # pragma: no cover - numba
    """:func:`find_echoes` without ``boost``, in one pass along the rows: each beam's open echo
    (first and last structure bin, evidence, pixel count, the maximum of the image from its
    first bin on) updated branch-free at every pixel - a dense, speckled mask (a hull filling
    70 % of its rows) defeats the branches of a walk over its pixels - and closed when the beam's
    next structure pixel lies more than ``max_gap`` bins on (bridged gap bins read then, in
    order: the same maximum) or at the last row.  Records by beam, then range."""
    n, m = mask.shape
    r0 = max(r0, 0)
    r1 = min(r1, n)
    step = max(max_gap, 0) + 1
    last = np.full(m, -step - 1, np.int64)       # last structure bin of the open echo
    first = np.zeros(m, np.int64)
    ev = np.zeros(m)
    npx = np.zeros(m, np.int64)
    vmax = np.zeros(m)
    # echoes are separated by more than max_gap background bins: an upper bound of their number
    cap = m * ((r1 - r0) // (step + 1) + 1)
    ri = np.empty((cap, 5), np.int64)             # beam, start, stop, peak, pixels
    rf = np.empty((cap, 4), np.float64)           # peak value, edge, slope, evidence
    k = 0
    events = np.arange(m)
    for i in range(r0, r1 + 1):
        # the beams with an event on this row, listed branch-free (in a speckled mask they are
        # unpredictable: the test per beam mispredicted; 4096 x 512 pings 1.4 -> 1.2 ms): a new
        # echo (the beam's open echo ends) or a gap bridged; every beam at r1, where all close
        c = m
        if i < r1:
            c = 0
            row = mask[i]
            for j in range(m):
                events[c] = j
                c += row[j] and i - last[j] > 1
        for t in range(c):
            j = events[t] if i < r1 else t
            L = last[j]
            if i < r1 and i - L <= step:
                for q in range(L + 1, i):
                    if img[q, j] > vmax[j]:
                        vmax[j] = img[q, j]
                continue
            if npx[j] > 0:
                s = first[j]
                p = s
                while p < L and not (img[p, j] >= peak_rel * vmax[j] and img[p, j] >= img[p + 1, j]):
                    p += 1
                pv, pos, sl = _edge_of_peak(img, j, s, p, fraction, back, forward)
                ri[k, 0], ri[k, 1], ri[k, 2], ri[k, 3], ri[k, 4] = j, s, L + 1, p, npx[j]
                rf[k, 0], rf[k, 1], rf[k, 2], rf[k, 3] = pv, pos, sl, ev[j]
                k += 1
                npx[j] = 0
            if i < r1:
                first[j] = i
                ev[j] = 0.0
                vmax[j] = img[i, j]
        if i == r1:
            break
        for j in range(m):
            st = mask[i, j]
            v = np.float64(img[i, j])
            e = lut[code[i, j]]
            vm = vmax[j]
            vmax[j] = v if (st and v > vm) else vm
            ev[j] = ev[j] + e if st else ev[j]
            npx[j] += st
            last[j] = i if st else last[j]
    # (np.int64: a counter that starts at a literal 0 would also compile the callee for Literal[int](0))
    return _records_by_beam(ri, rf, np.int64(k), m)


@njit(cache=True, nogil=True)
def _records_by_beam(ri, rf, k, m):  # pragma: no cover - numba
    """:func:`find_echoes`' arrays of the ``k`` echo records of :func:`_echoes_by_rows`, sorted by
    beam (stable: each beam's echoes are recorded in range order)."""
    cnt = np.zeros(m + 1, np.int64)
    for a in range(k):
        cnt[ri[a, 0] + 1] += 1
    for j in range(m):
        cnt[j + 1] += cnt[j]
    ints = np.empty((5, k), np.int64)
    floats = np.empty((4, k), np.float64)
    for a in range(k):
        t = cnt[ri[a, 0]]
        cnt[ri[a, 0]] = t + 1
        ints[:, t] = ri[a]
        floats[:, t] = rf[a]
    return (ints[0].copy(), ints[1].copy(), ints[2].copy(), ints[3].copy(), floats[0].copy(), floats[1].copy(),
            floats[2].copy(), floats[3].copy(), ints[4].copy())


@njit(cache=True, nogil=True)
def _echoes_of_columns(img, max_gap, fraction, peak_rel, back, forward, cols, col_first, rows,
                       pix):  # pragma: no cover - numba
    """The echoes of :func:`find_echoes` on the columns ``cols``, whose structure pixels are at
    rows ``rows[col_first[c] : col_first[c + 1]]`` (ascending) for column ``cols[c]``, with their
    image values and evidence in ``pix`` (see :func:`_column_pixels`).  An echo without gap rows
    reads the image along it from ``pix`` (contiguous; a walk down a column of a tall image
    misses the cache at every bin)."""
    n = img.shape[0]
    # echoes are separated by more than max_gap bins and hold a structure pixel each: an upper
    # bound of their number
    n_echoes = min(cols.size * (n // (max_gap + 2) + 1), rows.size)
    beam = np.empty(n_echoes, np.int64)
    start = np.empty(n_echoes, np.int64)
    stop = np.empty(n_echoes, np.int64)
    peak = np.empty(n_echoes, np.int64)
    peak_val = np.empty(n_echoes, np.float64)
    edge = np.empty(n_echoes, np.float64)
    slope = np.empty(n_echoes, np.float64)
    evidence_out = np.empty(n_echoes, np.float64)
    n_pix = np.empty(n_echoes, np.int64)
    step = max(max_gap, 0) + 1  # the farthest next structure pixel of the same echo
    k = 0
    for c in range(cols.size):
        j = cols[c]
        t = col_first[c]
        t_end = col_first[c + 1]
        while t < t_end:
            # an echo: structure pixels at most max_gap background bins apart
            s = rows[t]
            t0 = t
            last = s
            ev = 0.0
            npx = 0
            while t < t_end and rows[t] - last <= step:
                last = rows[t]
                ev += pix[t, 1]
                npx += 1
                t += 1
            e = last + 1
            # first peak: the first local maximum reaching peak_rel of the echo's maximum
            gap_free = npx == e - s
            if gap_free:  # no gap rows: img[s:e, j] is pix[t0:t, 0] (float64, exact)
                vmax = pix[t0, 0]
                for q in range(t0 + 1, t):
                    if pix[q, 0] > vmax:
                        vmax = pix[q, 0]
                u = t0
                while u < t - 1 and not (pix[u, 0] >= peak_rel * vmax and pix[u, 0] >= pix[u + 1, 0]):
                    u += 1
                p = s + (u - t0)
            else:
                vmax = img[s, j]
                for q in range(s + 1, e):
                    if img[q, j] > vmax:
                        vmax = img[q, j]
                p = s
                while p < e - 1 and not (img[p, j] >= peak_rel * vmax and img[p, j] >= img[p + 1, j]):
                    p += 1
            pv, pos, sl = _edge_of_peak(img, j, s, p, fraction, back, forward)
            beam[k] = j
            start[k] = s
            stop[k] = e
            peak[k] = p
            peak_val[k] = pv
            edge[k] = pos
            slope[k] = sl
            evidence_out[k] = ev
            n_pix[k] = npx
            k += 1
    return (beam[:k].copy(), start[:k].copy(), stop[:k].copy(), peak[:k].copy(), peak_val[:k].copy(),
            edge[:k].copy(), slope[:k].copy(), evidence_out[:k].copy(), n_pix[:k].copy())


@njit(cache=True, nogil=True, inline="always")
def _neighbours(a, b, g, pos, lo_bin, hi_bin, jump_bins, touch_bins):  # pragma: no cover - numba
    """The tracker's neighbour rule for echoes ``a`` and ``b`` ``g`` beams apart: their edges
    differ by at most ``jump_bins`` per beam and their bin intervals lie at most ``touch_bins`` per
    beam apart (a surface is contiguous across beams).  The contiguity test first: it has no
    division and fails for most pairs (echoes of other surfaces)."""
    if max(lo_bin[a] - hi_bin[b], lo_bin[b] - hi_bin[a]) > touch_bins * g:
        return False
    return not abs(pos[a] - pos[b]) / g > jump_bins


@njit(cache=True, nogil=True)
def _ordered_intervals(echo_beam, lo_bin, hi_bin):  # pragma: no cover - numba
    """Whether the bin intervals ``[lo_bin, hi_bin]`` of each beam's echoes (sorted by beam, then
    range) have both ends non-decreasing."""
    ok = True
    for a in range(echo_beam.size - 1):
        ok &= (echo_beam[a] != echo_beam[a + 1]) | ((lo_bin[a] <= lo_bin[a + 1]) & (hi_bin[a] <= hi_bin[a + 1]))
    return ok


@njit(cache=True, nogil=True)
def viterbi_surfaces(first, count, echo_beam, pos, lo_bin, hi_bin, unary, usable, max_gap, slope_bins, slope_cost,
                     jump_bins, touch_bins, segment_cost, gap_cost):  # pragma: no cover - numba
    """Best set of surface pieces over beams (exact dynamic programme; see
    :func:`sonarmap.ranges.tracking.track_surfaces`).

    ``first[j]``/``count[j]``: the echoes of beam ``j`` are ``first[j] .. first[j] + count[j] - 1``
    (sorted by range); ``pos``: their edge positions (bins); ``unary``: their cost (negative =
    evidence for structure); ``usable``: echoes still available.  A path is a sequence of echoes on
    increasing beams; consecutive echoes ``g <= max_gap + 1`` beams apart cost
    ``slope_cost * |d| / slope_bins`` (``d`` = their range difference per beam, bins) plus
    ``gap_cost * (g - 1)``, may not differ by more than ``jump_bins`` per beam and must be
    contiguous: their bin intervals ``[lo_bin, hi_bin]`` at most ``touch_bins * g`` apart; each piece
    costs ``segment_cost`` once.  Returns, per beam, the chosen echo index (-1 none).
    """
    m = first.size
    n_e = pos.size
    best = np.full(n_e, np.inf)
    prev = np.full(n_e, -1, np.int64)
    # best cost of any finished path up to (and including) beam j, and where it ends
    done = np.zeros(m + 1)
    done_end = np.full(m + 1, -1, np.int64)
    # with each beam's bin intervals in order (both ends non-decreasing, as find_echoes makes them)
    # the echoes of beam j - g that echo a can touch are one window: it starts after those ending
    # more than touch_bins * g before a starts (none of them touches a later echo of beam j either)
    # and ends before the first starting that far behind a ends - the same pairs in the same order
    ordered = _ordered_intervals(echo_beam, lo_bin, hi_bin)
    lead = np.empty(max_gap + 2, np.int64)
    for j in range(m):
        base = done[j]  # best finished before beam j (start a new piece here)
        for g in range(1, min(max_gap + 1, j) + 1):
            lead[g] = first[j - g]
        for a in range(first[j], first[j] + count[j]):
            if not usable[a]:
                continue
            c = base + segment_cost
            pa = -1
            for g in range(1, max_gap + 2):
                jb = j - g
                if jb < 0:
                    break
                b0 = first[jb]
                b1 = b0 + count[jb]
                reach = touch_bins * g
                if ordered:
                    b0 = lead[g]
                    while b0 < b1 and lo_bin[a] - hi_bin[b0] > reach:
                        b0 += 1
                    lead[g] = b0
                for b in range(b0, b1):
                    if ordered and lo_bin[b] - hi_bin[a] > reach:
                        break
                    if not usable[b] or best[b] == np.inf:
                        continue
                    if not _neighbours(a, b, g, pos, lo_bin, hi_bin, jump_bins, touch_bins):
                        continue
                    d = abs(pos[a] - pos[b]) / g
                    t = best[b] + slope_cost * d / slope_bins + gap_cost * (g - 1)
                    if t < c:
                        c = t
                        pa = b
            best[a] = c + unary[a]
            prev[a] = pa
        # finished paths: the best of "nothing new" and "a piece ending at beam j"
        done[j + 1] = done[j]
        done_end[j + 1] = done_end[j]
        for a in range(first[j], first[j] + count[j]):
            if usable[a] and best[a] < done[j + 1]:
                done[j + 1] = best[a]
                done_end[j + 1] = a
    chosen = np.full(m, -1, np.int64)
    # trace back: done_end[j] is the last echo of the best path over beams < j; pieces chain
    # through done[] at the beam where each piece starts
    j = m
    while j > 0:
        cur = done_end[j]
        if cur < 0:
            break
        while True:
            chosen[echo_beam[cur]] = cur
            if prev[cur] < 0:
                break
            cur = prev[cur]
        j = echo_beam[cur]
    return chosen


@njit(cache=True, nogil=True)
def bridge_surfaces(first, count, pos, lo_bin, hi_bin, unary, tracked, slope_bins, slope_cost, jump_bins,
                    touch_bins, max_beams):  # pragma: no cover - numba
    """Untracked echoes that bridge a tracked surface across beams another surface took (see
    :func:`sonarmap.ranges.tracking.track_surfaces`); returns the new ``tracked`` (bool per echo).

    Candidates: untracked echoes in front of every tracked echo of their beam, each a neighbour of
    a tracked or candidate echo on an adjacent beam whose step pays for itself (``unary + slope_cost
    * |d| / slope_bins < 0``), grown by forward and backward sweeps until none joins.  A chain of
    candidates on at most ``max_beams`` consecutive beams is kept when it is a neighbour of an
    echo tracked before at both ends; every other candidate is dropped.
    """
    m = first.size
    cand = _bridge_candidates(first, count, pos, lo_bin, hi_bin, unary, tracked, slope_bins, slope_cost, jump_bins,
                              touch_bins)
    out = tracked.copy()
    chain = np.empty(max_beams + 1, np.int64)
    for j in range(1, m):
        for a in range(first[j], first[j] + count[j]):
            if not cand[a]:
                continue
            if not _has_tracked_neighbour(a, j - 1, first, count, pos, lo_bin, hi_bin, tracked, jump_bins,
                                          touch_bins):
                continue
            n = 1
            chain[0] = a
            cur = a
            k = j
            while n <= max_beams and k + 1 < m:
                if _has_tracked_neighbour(cur, k + 1, first, count, pos, lo_bin, hi_bin, tracked, jump_bins,
                                          touch_bins):
                    for q in range(n):
                        out[chain[q]] = True
                    break
                nxt = -1
                for b in range(first[k + 1], first[k + 1] + count[k + 1]):
                    if cand[b] and _neighbours(cur, b, 1, pos, lo_bin, hi_bin, jump_bins, touch_bins):
                        nxt = b
                        break
                if nxt < 0 or n == max_beams:
                    break
                chain[n] = nxt
                n += 1
                cur = nxt
                k += 1
    return out


@njit(cache=True, nogil=True)
def _bridge_candidates(first, count, pos, lo_bin, hi_bin, unary, tracked, slope_bins, slope_cost, jump_bins,
                       touch_bins):  # pragma: no cover - numba
    """The candidates of :func:`bridge_surfaces` (bool per echo): untracked echoes in front of every
    tracked echo of their beam, each a neighbour of a tracked or candidate echo on an adjacent beam
    whose step pays for itself, grown by forward and backward sweeps until none joins."""
    m = first.size
    cand = np.zeros(tracked.size, np.bool_)
    changed = True
    while changed:
        changed = False
        for sweep in range(2):
            for t in range(m):
                j = t if sweep == 0 else m - 1 - t
                for a in range(first[j], first[j] + count[j]):
                    if tracked[a] or cand[a]:
                        continue
                    front = True
                    for q in range(first[j], first[j] + count[j]):
                        if (tracked[q] or cand[q]) and pos[q] <= pos[a]:
                            front = False
                            break
                    if not front:
                        continue
                    join = False
                    for jb in (j - 1, j + 1):
                        if jb < 0 or jb >= m:
                            continue
                        for b in range(first[jb], first[jb] + count[jb]):
                            if (tracked[b] or cand[b]) \
                                    and _neighbours(a, b, 1, pos, lo_bin, hi_bin, jump_bins, touch_bins) \
                                    and unary[a] + slope_cost * abs(pos[a] - pos[b]) / slope_bins < 0.0:
                                join = True
                                break
                        if join:
                            break
                    if join:
                        cand[a] = True
                        changed = True
    return cand


@njit(cache=True, nogil=True)
def _has_tracked_neighbour(b, jb, first, count, pos, lo_bin, hi_bin, tracked, jump_bins,
                           touch_bins):  # pragma: no cover - numba
    """Whether beam ``jb`` holds a tracked echo that is a neighbour of echo ``b`` (one beam apart)."""
    for q in range(first[jb], first[jb] + count[jb]):
        if tracked[q] and _neighbours(b, q, 1, pos, lo_bin, hi_bin, jump_bins, touch_bins):
            return True
    return False


@njit(cache=True, nogil=True)
def _holds_tracked(jb, first, count, tracked):  # pragma: no cover - numba
    """Whether beam ``jb`` holds a tracked echo."""
    for q in range(first[jb], first[jb] + count[jb]):
        if tracked[q]:
            return True
    return False


@njit(cache=True, nogil=True)
def _touches_tracked(b, jb, first, count, lo_bin, hi_bin, tracked, touch_bins):  # pragma: no cover - numba
    """Whether beam ``jb`` holds a tracked echo whose bin interval lies within ``touch_bins`` of
    echo ``b``'s (one beam apart; the contiguity half of :func:`_neighbours`, whatever the edges)."""
    for q in range(first[jb], first[jb] + count[jb]):
        if tracked[q] and max(lo_bin[b] - hi_bin[q], lo_bin[q] - hi_bin[b]) <= touch_bins:
            return True
    return False


@njit(cache=True, nogil=True)
def extend_ends(first, count, pos, lo_bin, hi_bin, unary, tracks, slope_bins, slope_cost, jump_bins, touch_bins,
                max_beams):  # pragma: no cover - numba
    """The end extensions of the tracked surfaces ``tracks`` (``(n_surfaces, m)`` echo indices,
    nearest first; :func:`sonarmap.ranges.tracking.tracks_and_front`): per beam the nearest echo
    of an extension (-1 none) and whether there is any.

    Candidates are those of a bridge (:func:`_bridge_candidates`: untracked echoes in front of
    every tracked echo of their beam, each step a neighbour whose evidence pays for its slope).  A
    chain of candidates on consecutive beams is an extension when it starts beside a tracked echo
    where that echo's surface ends (no tracked echo on the chain's first beam lies within
    ``touch_bins`` of its bin interval, whatever their edges), every beam of it holds a tracked
    echo behind it (another surface took the beam), and it ends within ``max_beams`` beams: the
    next beam holds no candidate neighbour and no tracked neighbour (a chain that reaches a tracked
    echo again is a bridge's business)."""
    m = first.size
    n_e = pos.size
    chosen = np.full(m, -1, np.int64)
    tracked = np.zeros(n_e, np.bool_)
    for r in range(tracks.shape[0]):
        for j in range(m):
            if tracks[r, j] >= 0:
                tracked[tracks[r, j]] = True
    cand = _bridge_candidates(first, count, pos, lo_bin, hi_bin, unary, tracked, slope_bins, slope_cost, jump_bins,
                              touch_bins)
    hit = False
    chain = np.empty(max_beams + 1, np.int64)
    for d in (-1, 1):  # the chain grows towards lower (-1) or higher (+1) beams from its anchor
        for j in range(m):
            ja = j - d  # the anchor's beam
            if ja < 0 or ja >= m or not _holds_tracked(j, first, count, tracked):  # (another surface took j)
                continue
            for a in range(first[j], first[j] + count[j]):
                if not cand[a]:
                    continue
                anchored = False
                for b in range(first[ja], first[ja] + count[ja]):
                    if tracked[b] and _neighbours(a, b, 1, pos, lo_bin, hi_bin, jump_bins, touch_bins) \
                            and not _touches_tracked(b, j, first, count, lo_bin, hi_bin, tracked, touch_bins):
                        anchored = True
                        break
                if not anchored:
                    continue
                n = 1
                chain[0] = a
                cur = a
                k = j
                ok = True
                while True:
                    kn = k + d
                    if kn < 0 or kn >= m:
                        break
                    if _has_tracked_neighbour(cur, kn, first, count, pos, lo_bin, hi_bin, tracked, jump_bins,
                                              touch_bins):
                        ok = False  # a bridge, or none: not an end
                        break
                    nxt = -1
                    for b in range(first[kn], first[kn] + count[kn]):
                        if cand[b] and _neighbours(cur, b, 1, pos, lo_bin, hi_bin, jump_bins, touch_bins):
                            nxt = b
                            break
                    if nxt < 0:
                        break
                    if not _holds_tracked(kn, first, count, tracked) or n == max_beams:
                        ok = False
                        break
                    chain[n] = nxt
                    n += 1
                    cur = nxt
                    k = kn
                if ok:
                    for q in range(n):
                        c = chain[q]
                        jc = j + d * q
                        if chosen[jc] < 0 or pos[c] < pos[chosen[jc]]:
                            chosen[jc] = c
                        hit = True
    return chosen, hit


@njit(cache=True, nogil=True, inline="always")
def _key_less(a, b):  # pragma: no cover - numba
    """``a`` sorts before ``b`` as in numpy (NaN last)."""
    return a < b or (np.isnan(b) and not np.isnan(a))


@njit(cache=True, nogil=True)
def beam_index(echo_beam, m):  # pragma: no cover - numba
    """``(first, count)``: the echoes (sorted by beam) of beam ``j`` are ``first[j] .. first[j] +
    count[j] - 1``."""
    count = np.zeros(m, np.int64)
    for a in range(echo_beam.size):
        count[echo_beam[a]] += 1
    first = np.zeros(m, np.int64)
    for j in range(1, m):
        first[j] = first[j - 1] + count[j - 1]
    return first, count


@njit(cache=True, nogil=True)
def front_pass(first, count, echo_beam, tracks, pos, lo_bin, hi_bin, unary, max_gap, slope_bins, slope_cost,
               jump_bins, touch_bins, segment_cost, gap_cost, point_on, peak_val, point, clip_rise, evidence,
               width_beams, pulse_bins, flat_bins, point_jump_bins, dip, over_range, margin,
               fraction):  # pragma: no cover - numba
    """The front pass (:func:`sonarmap.ranges.tracking.front_surfaces`) of the tracked surfaces
    ``tracks`` (``(n_surfaces, m)`` echo indices, nearest first): one :func:`viterbi_surfaces`
    pass over the untracked echoes whose bin interval ends before that of their beam's nearest
    tracked echo starts, its point pieces (:func:`point_pieces`, with ``point_on``) dropped.
    Returns per beam the pass's echo (-1 none) and whether it chose any."""
    m = tracks.shape[1]
    n_e = pos.size
    chosen = np.full(m, -1, np.int64)
    usable = np.zeros(n_e, np.bool_)
    tracked = np.zeros(n_e, np.bool_)
    for r in range(tracks.shape[0]):
        for j in range(m):
            if tracks[r, j] >= 0:
                tracked[tracks[r, j]] = True
    any_usable = False
    for a in range(n_e):
        near = tracks[0, echo_beam[a]]
        if near >= 0 and not tracked[a] and hi_bin[a] < lo_bin[near]:
            usable[a] = True
            any_usable = True
    if not any_usable:
        return chosen, False
    chosen = viterbi_surfaces(first, count, echo_beam, pos, lo_bin, hi_bin, unary, usable, max_gap, slope_bins,
                              slope_cost, jump_bins, touch_bins, segment_cost, gap_cost)
    hit = False
    if point_on:
        drop = point_pieces(chosen, pos, peak_val, point, clip_rise, evidence, width_beams, lo_bin, hi_bin, max_gap,
                            jump_bins, touch_bins, pulse_bins, flat_bins, point_jump_bins, dip, over_range, margin,
                            fraction)
        for j in range(m):
            if drop[j]:
                chosen[j] = -1
    for j in range(m):
        if chosen[j] >= 0:
            hit = True
    return chosen, hit


@njit(cache=True, nogil=True)
def with_front(tracks, chosen):  # pragma: no cover - numba
    """``tracks`` with the front pass's echoes ``chosen`` (per beam, -1 none) as the nearest
    surfaces (a new array; the farthest surface of a full beam drops off)."""
    out = tracks.copy()
    n = tracks.shape[0]
    for j in range(tracks.shape[1]):
        if chosen[j] >= 0:
            for r in range(n - 1, 0, -1):
                out[r, j] = tracks[r - 1, j]
            out[0, j] = chosen[j]
    return out


@njit(cache=True, nogil=True)
def clip_rises(edge_bin, peak_bin, clipped, clip_row, has_clipped, has_row):  # pragma: no cover - numba
    """:func:`sonarmap.ranges.tracking.clip_rise` (``has_clipped`` / ``has_row``: whether
    ``clipped`` / ``clip_row`` are known): -1 for an echo that is not clipped, 0 for a clipped one,
    ``max(clip_row - edge_bin, 0)`` (NaN stays NaN, as numpy's maximum) for one whose first peak
    is clipped (its first full-scale row at most a bin behind ``peak_bin``)."""
    n = edge_bin.size
    out = np.full(n, -1.0)
    if not has_clipped:
        return out
    for k in range(n):
        if not clipped[k]:
            continue
        out[k] = 0.0
        if has_row and clip_row[k] >= 0 and clip_row[k] <= peak_bin[k] + 1:
            d = clip_row[k] - edge_bin[k]
            out[k] = d if (d >= 0.0 or np.isnan(d)) else 0.0
    return out


@njit(cache=True, nogil=True)
def track_inputs(edge_bin, start_bin, stop_bin, evidence, n_pixels, peak_bin, clipped, clip_row, has_clipped,
                 has_row, beam_cost, point_llr):  # pragma: no cover - numba
    """The per-echo inputs of :func:`track_surfaces` (numpy's arithmetic, element by element):
    the bin intervals (``Echoes.intervals``: ``min(start_bin, floor(edge_bin))``, ``stop_bin - 1``),
    the unary ``beam_cost - evidence``, the point echoes (``evidence >= point_llr x n_pixels``)
    and :func:`clip_rises`."""
    n = edge_bin.size
    lo = np.empty(n, np.int64)
    hi = np.empty(n, np.int64)
    unary = np.empty(n)
    point = np.empty(n, np.bool_)
    for k in range(n):
        x = np.floor(edge_bin[k])
        f = np.iinfo(np.int64).min if np.isnan(x) else int(x)  # numpy's cast of NaN on x86
        lo[k] = min(start_bin[k], f)
        hi[k] = stop_bin[k] - 1
        unary[k] = beam_cost - evidence[k]
        point[k] = evidence[k] >= point_llr * n_pixels[k]
    return lo, hi, unary, point, clip_rises(edge_bin, peak_bin, clipped, clip_row, has_clipped, has_row)


@njit(cache=True, nogil=True)
def track_surfaces(echo_beam, m, pos, lo_bin, hi_bin, unary, n_surfaces, max_gap, slope_bins, slope_cost, jump_bins,
                   touch_bins, segment_cost, gap_cost, bridge_beams, extend_beams, point_on, peak_val, point, clip_rise,
                   evidence, width_beams, pulse_bins, flat_bins, point_jump_bins, dip, over_range, margin,
                   fraction, front):  # pragma: no cover - numba
    """:func:`sonarmap.ranges.tracking.track_surfaces` in one kernel: ``n_surfaces`` passes of
    :func:`viterbi_surfaces` (each on the echoes the earlier ones left; with ``point_on`` a pass's
    point pieces, :func:`point_pieces` with the arguments after it, are not kept), the bridges
    (:func:`bridge_surfaces`; over one beam the nearest bridge wins, on equal edges the later
    echo), and per beam the surfaces sorted by edge (stable, NaN last) and cut to ``n_surfaces``.
    Returns the ``(n_surfaces, m)`` echo indices (-1: none), with ``front`` the same after the
    front pass and the end extensions (``extend_beams`` > 0) of its result (:func:`front_pass`,
    :func:`extend_ends`, :func:`with_front`; the same array when they keep nothing or without
    ``front``), and whether they kept anything."""
    first, count = beam_index(echo_beam, m)
    out = _tracked(first, count, echo_beam, m, pos, lo_bin, hi_bin, unary, n_surfaces, max_gap, slope_bins,
                   slope_cost, jump_bins, touch_bins, segment_cost, gap_cost, bridge_beams, point_on, peak_val, point,
                   clip_rise, evidence, width_beams, pulse_bins, flat_bins, point_jump_bins, dip, over_range, margin,
                   fraction)
    if not front or pos.size == 0:
        return out, out, False
    after, hit = front_and_extensions(first, count, echo_beam, out, pos, lo_bin, hi_bin, unary, max_gap, slope_bins,
                                      slope_cost, jump_bins, touch_bins, segment_cost, gap_cost, extend_beams,
                                      point_on, peak_val, point, clip_rise, evidence, width_beams, pulse_bins,
                                      flat_bins, point_jump_bins, dip, over_range, margin, fraction)
    return out, after, hit


@njit(cache=True, nogil=True)
def front_and_extensions(first, count, echo_beam, tracks, pos, lo_bin, hi_bin, unary, max_gap, slope_bins,
                         slope_cost, jump_bins, touch_bins, segment_cost, gap_cost, extend_beams, point_on, peak_val,
                         point, clip_rise, evidence, width_beams, pulse_bins, flat_bins, point_jump_bins, dip,
                         over_range, margin, fraction):  # pragma: no cover - numba
    """:func:`front_pass` of ``tracks`` and then, with ``extend_beams`` > 0, :func:`extend_ends` of
    its result, each one's echoes made the beams' nearest surfaces (:func:`with_front`): the new
    tracks (``tracks`` itself when neither keeps anything) and whether either kept anything
    (:func:`sonarmap.ranges.tracking.front_surfaces`)."""
    chosen, hit = front_pass(first, count, echo_beam, tracks, pos, lo_bin, hi_bin, unary, max_gap, slope_bins,
                             slope_cost, jump_bins, touch_bins, segment_cost, gap_cost, point_on, peak_val, point,
                             clip_rise, evidence, width_beams, pulse_bins, flat_bins, point_jump_bins, dip, over_range,
                             margin, fraction)
    after = with_front(tracks, chosen) if hit else tracks
    if extend_beams > 0:
        more, grown = extend_ends(first, count, pos, lo_bin, hi_bin, unary, after, slope_bins, slope_cost, jump_bins,
                                  touch_bins, extend_beams)
        if grown:
            after = with_front(after, more)
            hit = True
    return after, hit


@njit(cache=True, nogil=True)
def tracked_echoes(edge_bin, start_bin, stop_bin, evidence, n_pixels, peak_bin, clipped, clip_row, has_clipped, has_row,
                   beam_cost, point_llr, echo_beam, m, n_surfaces, max_gap, slope_bins, slope_cost, jump_bins,
                   touch_bins, segment_cost, gap_cost, bridge_beams, extend_beams, point_on, peak_val, point_evidence,
                   width_beams, pulse_bins, flat_bins, point_jump_bins, dip, over_range, margin, fraction,
                   front):  # pragma: no cover - numba
    """:func:`track_inputs` (its arguments first) and :func:`track_surfaces` of the echoes at
    ``edge_bin`` with them (the point echoes and clip rises only with ``point_on``, empty
    otherwise; ``point_evidence``: the evidence its point rule reads) in one call."""
    lo, hi, unary, point, rise = track_inputs(edge_bin, start_bin, stop_bin, evidence, n_pixels, peak_bin, clipped,
                                              clip_row, has_clipped, has_row, beam_cost, point_llr)
    k = point.size if point_on else 0
    return track_surfaces(echo_beam, m, edge_bin, lo, hi, unary, n_surfaces, max_gap, slope_bins, slope_cost,
                          jump_bins, touch_bins, segment_cost, gap_cost, bridge_beams, extend_beams, point_on, peak_val,
                          point[:k], rise[:k], point_evidence, width_beams, pulse_bins, flat_bins, point_jump_bins, dip,
                          over_range, margin, fraction, front)


@njit(cache=True, nogil=True)
def _tracked(first, count, echo_beam, m, pos, lo_bin, hi_bin, unary, n_surfaces, max_gap, slope_bins, slope_cost,
             jump_bins, touch_bins, segment_cost, gap_cost, bridge_beams, point_on, peak_val, point, clip_rise,
             evidence, width_beams, pulse_bins, flat_bins, point_jump_bins, dip, over_range, margin,
             fraction):  # pragma: no cover - numba
    """:func:`track_surfaces` without the front pass (``first``, ``count``: :func:`beam_index`)."""
    n_e = pos.size
    out = np.full((n_surfaces, m), -1, np.int64)
    if n_e == 0:
        return out
    usable = np.ones(n_e, np.bool_)
    picks = np.full((n_surfaces + 1, m), -1, np.int64)
    n_picks = 0
    for _ in range(n_surfaces):
        chosen = viterbi_surfaces(first, count, echo_beam, pos, lo_bin, hi_bin, unary, usable, max_gap, slope_bins,
                                  slope_cost, jump_bins, touch_bins, segment_cost, gap_cost)
        hit = False
        for j in range(m):
            if chosen[j] >= 0:
                hit = True
        if not hit:
            break
        for j in range(m):
            if chosen[j] >= 0:
                usable[chosen[j]] = False  # point pieces included: their echoes are not tracked again
        if point_on:
            drop = point_pieces(chosen, pos, peak_val, point, clip_rise, evidence, width_beams, lo_bin, hi_bin,
                                max_gap, jump_bins, touch_bins, pulse_bins, flat_bins, point_jump_bins, dip,
                                over_range, margin, fraction)
            hit = False
            for j in range(m):
                if drop[j]:
                    chosen[j] = -1
                elif chosen[j] >= 0:
                    hit = True
            if not hit:
                continue
        for j in range(m):
            picks[n_picks + 1, j] = chosen[j]
        n_picks += 1
    if n_picks == 0:
        return out
    row0 = 1  # picks[0] holds the bridges, if any
    if bridge_beams > 0:
        tracked = np.zeros(n_e, np.bool_)
        for p in range(1, n_picks + 1):
            for j in range(m):
                if picks[p, j] >= 0:
                    tracked[picks[p, j]] = True
        bridged = bridge_surfaces(first, count, pos, lo_bin, hi_bin, unary, tracked, slope_bins, slope_cost,
                                  jump_bins, touch_bins, bridge_beams)
        for a in range(n_e):
            if bridged[a] and not tracked[a]:
                j = echo_beam[a]
                b = picks[0, j]
                # the nearest bridge of the beam; of equal edges the later echo
                if b < 0 or not _key_less(-pos[a], -pos[b]):
                    picks[0, j] = a
                row0 = 0
    n_rows = n_picks + 1 - row0
    idx = np.empty(n_rows, np.int64)
    key = np.empty(n_rows)
    for j in range(m):
        # stable insertion sort by edge (no surface: +inf)
        for r in range(n_rows):
            e = picks[row0 + r, j]
            k = pos[e] if e >= 0 else np.inf
            q = r
            while q > 0 and _key_less(k, key[q - 1]):
                idx[q] = idx[q - 1]
                key[q] = key[q - 1]
                q -= 1
            idx[q] = e
            key[q] = k
        for r in range(min(n_rows, n_surfaces)):
            out[r, j] = idx[r]
    return out


# ----------------------------------------------------------------------------- components and edges


@njit(cache=True, nogil=True)
def _find(parent, a):  # pragma: no cover - numba
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def _union_back_neighbours(idx, parent, a, i, j, w):  # pragma: no cover - numba
    """Union node ``a`` at ``(i, j)`` with its already-visited 8-neighbours in a raster scan,
    ``(i, j-1)``, ``(i-1, j-1)``, ``(i-1, j)``, ``(i-1, j+1)`` (smaller root wins)."""
    for di, dj in ((0, -1), (-1, -1), (-1, 0), (-1, 1)):
        ii = i + di
        jj = j + dj
        if 0 <= ii and 0 <= jj < w:
            b = idx[ii, jj]
            if b >= 0:
                ra = _find(parent, a)
                rb = _find(parent, b)
                if ra != rb:
                    if ra < rb:
                        parent[rb] = ra
                    else:
                        parent[ra] = rb


@njit(cache=True, nogil=True, inline="always")
def _empty_extents(n, h, w):  # pragma: no cover - numba
    """``(imin, imax, jmin, jmax)`` of ``n`` components on an ``(h, w)`` lattice before any pixel
    (:func:`_grow_box` extends them)."""
    return (np.full(n, h, dtype=np.int32), np.full(n, -1, dtype=np.int32), np.full(n, w, dtype=np.int32),
            np.full(n, -1, dtype=np.int32))


@njit(cache=True, nogil=True, inline="always")
def _grow_box(r, i, j, imin, imax, jmin, jmax):  # pragma: no cover - numba
    """Extend component ``r``'s bin (``i``) and beam (``j``) extent by pixel ``(i, j)``."""
    if j < jmin[r]:
        jmin[r] = j
    if j > jmax[r]:
        jmax[r] = j
    if i < imin[r]:
        imin[r] = i
    if i > imax[r]:
        imax[r] = i


@njit(cache=True, nogil=True, inline="always")
def _is_wide(r, imin, imax, jmin, jmax, min_beams, min_bins):  # pragma: no cover - numba
    """Component ``r`` spans >= ``min_beams`` beams, or >= ``min_bins`` bins (``min_bins <= 0``: off)."""
    return jmax[r] - jmin[r] + 1 >= min_beams or (min_bins > 0 and imax[r] - imin[r] + 1 >= min_bins)


@njit(cache=True, nogil=True)
def wide_components(mask, seeds, min_beams, min_bins):  # pragma: no cover - numba
    """Keep 8-connected components of ``mask`` that contain a ``seeds`` pixel and span
    >= ``min_beams`` beams or >= ``min_bins`` bins.

    Union-find over the true pixels (raster order, 4 already-visited neighbours), then the beam
    and bin extent of every component.  ``min_bins <= 0`` disables the bin test; pass
    ``seeds = mask`` to keep components regardless of seeds.
    """
    h, w = mask.shape
    idx = np.full((h, w), -1, dtype=np.int32)
    n = 0
    for i in range(h):
        for j in range(w):
            if mask[i, j]:
                idx[i, j] = n
                n += 1
    parent = np.arange(n, dtype=np.int32)
    for i in range(h):
        for j in range(w):
            a = idx[i, j]
            if a < 0:
                continue
            _union_back_neighbours(idx, parent, a, i, j, w)
    imin, imax, jmin, jmax = _empty_extents(n, h, w)
    seeded = np.zeros(n, dtype=np.bool_)
    for i in range(h):
        for j in range(w):
            a = idx[i, j]
            if a >= 0:
                r = _find(parent, a)
                if seeds[i, j]:
                    seeded[r] = True
                _grow_box(r, i, j, imin, imax, jmin, jmax)
    out = np.zeros((h, w), dtype=np.bool_)
    for i in range(h):
        for j in range(w):
            a = idx[i, j]
            if a >= 0:
                r = _find(parent, a)
                if seeded[r] and _is_wide(r, imin, imax, jmin, jmax, min_beams, min_bins):
                    out[i, j] = True
    return out


@njit(cache=True, nogil=True)
def first_runs(mask, min_run):  # pragma: no cover - numba
    """Per column, the first row starting a run of ``min_run`` true pixels (-1 if none)."""
    h, w = mask.shape
    out = np.full(w, -1, dtype=np.int64)
    for j in range(w):
        run = 0
        for i in range(h):
            if mask[i, j]:
                run += 1
                if run >= min_run:
                    out[j] = i - min_run + 1
                    break
            else:
                run = 0
    return out


@njit(cache=True, nogil=True)
def near_mask(kept, rest, gap):  # pragma: no cover - numba
    """``rest`` pixels within ``gap`` beams and 1 bin of a ``kept`` pixel."""
    h, w = kept.shape
    out = np.zeros((h, w), dtype=np.bool_)
    any_hit = False
    for i in range(h):
        for j in range(w):
            if kept[i, j]:
                for ii in range(max(i - 1, 0), min(i + 2, h)):
                    for jj in range(max(j - gap, 0), min(j + gap + 1, w)):
                        if rest[ii, jj]:
                            out[ii, jj] = True
                            any_hit = True
    return out, any_hit


@njit(cache=True, nogil=True)
def refine_leading_edge(img, bins, k_max, level):  # pragma: no cover - numba
    """Move each first return up while the 3 bin x 3 beam mean above it is >= ``level``."""
    h, w = img.shape
    out = bins.copy()
    for j in range(w):
        b = bins[j]
        if b < 0:
            continue
        j0 = max(j - 1, 0)
        j1 = min(j + 2, w)
        for _ in range(k_max):
            r = b - 1
            if r < 0:
                break
            i0 = max(r - 1, 0)
            i1 = min(r + 2, h)
            s = 0.0
            for ii in range(i0, i1):
                for jj in range(j0, j1):
                    s += img[ii, jj]
            if s / ((i1 - i0) * (j1 - j0)) >= level:
                b = r
            else:
                break
        out[j] = b
    return out


@njit(cache=True, nogil=True)
def _row_runs(mask):  # pragma: no cover - numba
    """The runs of true pixels of every row: ``(first, start, stop)``, row ``i``'s runs being
    ``first[i]:first[i + 1]`` in beam order, run ``k`` covering beams ``start[k]..stop[k]``.
    Rows of a multiple of 8 pixels are read 8 at a time where all 8 are false (between runs) or
    all true (inside one)."""
    h, w = mask.shape
    first = np.empty(h + 1, dtype=np.int64)
    start = np.empty(h * ((w + 1) // 2), dtype=np.int32)
    stop = np.empty(h * ((w + 1) // 2), dtype=np.int32)
    flat = mask.reshape(h * w).view(np.uint8)
    by_words = w % 8 == 0
    words = flat.view(np.uint64) if by_words else np.zeros(0, np.uint64)
    full = np.uint64(0x0101010101010101)  # 8 true pixels (a bool is byte 0 or 1)
    k = 0
    for i in range(h):
        first[i] = k
        base = i * w
        j = 0
        while j < w:
            if by_words and (j & 7) == 0 and words[(base + j) >> 3] == 0:
                j += 8
                continue
            if flat[base + j]:
                start[k] = j
                while j < w and flat[base + j]:
                    if by_words and (j & 7) == 0 and words[(base + j) >> 3] == full:
                        j += 8
                    else:
                        j += 1
                stop[k] = j - 1
                k += 1
            j += 1
    first[h] = k
    return first, start[:k], stop[:k]


@njit(cache=True, nogil=True)
def _run_roots(first, start, stop):  # pragma: no cover - numba
    """8-connected components of the runs: each run's root run (union-find, smaller root wins).
    Runs of consecutive rows touch when their beam intervals, one widened by a beam each side,
    overlap."""
    n = start.size
    parent = np.arange(n, dtype=np.int32)
    for i in range(1, first.size - 1):
        a, a_end = first[i], first[i + 1]
        b, b_end = first[i - 1], first[i]
        while a < a_end and b < b_end:
            if stop[b] < start[a] - 1:
                b += 1
            elif stop[a] < start[b] - 1:
                a += 1
            else:
                ra = _find(parent, a)
                rb = _find(parent, b)
                if ra < rb:
                    parent[rb] = ra
                elif rb < ra:
                    parent[ra] = rb
                if stop[a] < stop[b]:
                    a += 1
                else:
                    b += 1
    for a in range(n):
        parent[a] = _find(parent, a)
    return parent


@njit(cache=True, nogil=True)
def _link_round(first, start, stop, root, kept, add, gap):  # pragma: no cover - numba
    """Mark in ``add`` every component not in ``kept`` with a pixel within ``gap`` beams and 1 bin
    of a ``kept`` component's pixel; True if any."""
    hit = False
    for i in range(first.size - 1):
        nxt = first[i + 1]
        b0 = nxt
        b_end = first[i + 2] if i + 2 < first.size else nxt
        for a in range(first[i], first[i + 1]):
            ka = kept[root[a]]
            # the later runs of the same row, then the runs of the next row, within gap beams
            for b in range(a + 1, nxt):
                if start[b] - stop[a] > gap:
                    break
                if kept[root[b]] != ka:
                    add[root[a] if kept[root[b]] else root[b]] = True
                    hit = True
            while b0 < b_end and stop[b0] < start[a] - gap:
                b0 += 1
            for b in range(b0, b_end):
                if start[b] - stop[a] > gap:
                    break
                if kept[root[b]] != ka:
                    add[root[a] if kept[root[b]] else root[b]] = True
                    hit = True
    return hit


@njit(cache=True, nogil=True)
def linked_components(mask, min_beams, min_bins, gap, rounds, min_pixels, rule, range_m, azimuth, dr, daz,
                      min_extent):  # pragma: no cover - numba
    """Rule 0 of :func:`sonarmap.ranges.extract_ranges` and the metric extent rule in one kernel.

    With ``rule``: the 8-connected components of ``mask`` spanning >= ``min_beams`` beams or
    >= ``min_bins`` bins (``min_bins <= 0``: beams only) or holding >= ``min_pixels`` pixels
    (``min_pixels <= 0``: off), then up to ``rounds`` rounds adding every other component with a
    pixel within ``gap`` beams and 1 bin of a pixel kept at the start of the round (stopping at the
    first round that adds nothing); without: every component.  Then, when ``min_extent > 0``, the
    kept components smaller than ``min_extent`` both across range (``max |range_m|`` of their first
    and last bin times their azimuth extent plus ``daz``) and along range (bins times ``dr``) are
    dropped (:func:`sonarmap.ranges.drop_small_components`).

    Same result as :func:`wide_components` followed by ``_link_components`` (whose components of
    ``mask & ~kept`` are exactly the components of ``mask`` not kept yet), but on runs of pixels:
    the lattice is labelled once, and the kept components are the components of the result.
    """
    h, w = mask.shape
    first, start, stop = _row_runs(mask)
    root = _run_roots(first, start, stop)
    n = start.size
    imin = np.full(n, h, dtype=np.int64)
    imax = np.full(n, -1, dtype=np.int64)
    jmin = np.full(n, w, dtype=np.int64)
    jmax = np.full(n, -1, dtype=np.int64)
    npx = np.zeros(n, dtype=np.int64)
    for i in range(h):
        for a in range(first[i], first[i + 1]):
            r = root[a]
            imin[r] = min(imin[r], i)
            imax[r] = i
            jmin[r] = min(jmin[r], start[a])
            jmax[r] = max(jmax[r], stop[a])
            npx[r] += stop[a] - start[a] + 1
    kept = np.zeros(n, dtype=np.bool_)
    for a in range(n):
        if root[a] == a:
            kept[a] = not rule or (_is_wide(a, imin, imax, jmin, jmax, min_beams, min_bins)
                                   or (min_pixels > 0 and npx[a] >= min_pixels))
    if rule:
        add = np.zeros(n, dtype=np.bool_)
        for _ in range(rounds):
            if not _link_round(first, start, stop, root, kept, add, gap):
                break
            for a in range(n):
                if add[a]:
                    kept[a] = True
                    add[a] = False
    if min_extent > 0:
        for a in range(n):
            if kept[a]:
                i0, i1 = imin[a], imax[a]
                far = _max_nan(abs(range_m[i1]), abs(range_m[i0]))
                cross = far * (abs(azimuth[jmax[a]] - azimuth[jmin[a]]) + daz)
                along = (i1 - i0 + 1) * dr
                kept[a] = _max_nan(cross, along) >= min_extent
    out = np.zeros((h, w), dtype=np.bool_)
    for i in range(h):
        for a in range(first[i], first[i + 1]):
            if kept[root[a]]:
                out[i, start[a]:stop[a] + 1] = True
    return out


@njit(cache=True, nogil=True)
def continued_bands(band, min_beams, seeds, link_beams, link_bins):  # pragma: no cover - numba
    """The 8-connected components of ``band`` spanning >= ``min_beams`` beams, or with an empty
    ``min_beams <= 0`` holding a ``seeds`` pixel, and every further component that continues them
    across beams (band pooling's short pieces of a surface).

    Rounds, each judged on the components kept at its start, until one adds nothing: a component
    is added when one of its pixels lies ``d`` = 2..``link_beams`` beams from a kept pixel and at
    most ``link_bins`` bins per beam (``floor(link_bins d)``) from it in range, and at most half of
    the beams it spans hold a kept
    pixel (it adds beams to the surface; over beams the kept bands already hold it is another
    layer - a fish, a second surface - not their continuation).  Returns the kept pixels.
    """
    h, w = band.shape
    first, start, stop = _row_runs(band)
    root = _run_roots(first, start, stop)
    n = start.size
    row = np.empty(n, dtype=np.int64)
    jmin = np.full(n, w, dtype=np.int64)
    jmax = np.full(n, -1, dtype=np.int64)
    kept = np.zeros(n, dtype=np.bool_)
    for i in range(h):
        for a in range(first[i], first[i + 1]):
            row[a] = i
            r = root[a]
            jmin[r] = min(jmin[r], start[a])
            jmax[r] = max(jmax[r], stop[a])
            if min_beams <= 0 and not kept[r]:
                for j in range(start[a], stop[a] + 1):
                    if seeds[i, j]:
                        kept[r] = True
                        break
    rest = 0  # components not kept
    for r in range(n):
        if root[r] == r:
            if min_beams > 0:
                kept[r] = jmax[r] - jmin[r] + 1 >= min_beams
            rest += not kept[r]
    out = np.zeros((h, w), dtype=np.bool_)
    for a in range(n):
        if kept[root[a]]:
            out[row[a], start[a]:stop[a] + 1] = True
    if link_beams < 2 or rest == 0 or rest == n:
        return out
    count = np.empty((h + 1, w), dtype=np.int32)  # kept pixels of each column above each row
    count[0] = 0
    taken = np.zeros(w + 1, dtype=np.int64)  # columns holding a kept pixel, cumulative
    near = np.zeros(n, dtype=np.bool_)
    while True:
        # row by row over every column (contiguous, it vectorises: 1.7x faster than the columns
        # one by one, even than only the columns a round changed - most pings take one round)
        for i in range(h):
            for j in range(w):
                count[i + 1, j] = count[i, j] + out[i, j]
        for j in range(w):
            taken[j + 1] = taken[j] + (count[h, j] > 0)
        near[:] = False
        for a in range(n):
            r = root[a]
            if kept[r] or near[r]:
                continue
            i = row[a]
            for j in range(start[a], stop[a] + 1):
                for d in range(2, link_beams + 1):
                    reach = max(int(link_bins * d), 1)
                    lo = max(i - reach, 0)
                    hi = min(i + reach + 1, h)
                    if ((j - d >= 0 and count[hi, j - d] > count[lo, j - d])
                            or (j + d < w and count[hi, j + d] > count[lo, j + d])):
                        near[r] = True
                        break
                if near[r]:
                    break
        added = False
        for r in range(n):
            if near[r] and root[r] == r and 2 * (taken[jmax[r] + 1] - taken[jmin[r]]) <= jmax[r] - jmin[r] + 1:
                kept[r] = True
                added = True
        if not added:
            return out
        for a in range(n):
            r = root[a]
            if near[r] and kept[r]:
                out[row[a], start[a]:stop[a] + 1] = True


@njit(cache=True, nogil=True, inline="always")
def _max_nan(a, b):  # pragma: no cover - numba
    """``np.maximum`` of two floats (NaN if either is)."""
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@njit(cache=True, nogil=True)
def support_counts(bins, neighbour_beams, max_jump):  # pragma: no cover - numba
    """Per beam ``(number of supporting neighbours, number of existing neighbours)``: beam ``k``
    with ``0 < |k - j| <= neighbour_beams`` exists if it lies in range and supports ``j`` if both
    have a return (``bin >= 0``) within ``max_jump`` bins."""
    n = bins.size
    sup = np.zeros(n, dtype=np.int64)
    cnt = np.zeros(n, dtype=np.int64)
    for j in range(n):
        bj = bins[j]
        for k in range(max(j - neighbour_beams, 0), min(j + neighbour_beams + 1, n)):
            if k == j:
                continue
            cnt[j] += 1
            bk = bins[k]
            if bj >= 0 and bk >= 0 and abs(bj - bk) <= max_jump:
                sup[j] += 1
    return sup, cnt


@njit(cache=True, nogil=True)
def half_peak_edges(img, mask, bins, fraction):  # pragma: no cover - numba
    """Per beam with ``bins[j] >= 0``: the leading edge of the echo that starts there.

    The peak is the first local maximum of ``img`` along the run of ``mask`` from ``bins[j]`` (at
    least that bin); the edge is the first bin of the run reaching ``fraction`` x the peak.
    Returns ``(edge_bin, frac)``: the crossing lies ``frac`` of a bin before ``edge_bin`` (0 when
    it is exactly there or at the run's start).  See :func:`sonarmap.ranges.half_peak_edges`.
    """
    n, m = img.shape
    out = bins.copy()
    frac = np.zeros(m)
    for j in range(m):
        b = bins[j]
        if b < 0:
            continue
        end = b
        while end + 1 < n and mask[end + 1, j]:
            end += 1
        k = b
        while k < end and img[k + 1, j] >= img[k, j]:
            k += 1
        level = fraction * img[k, j]
        e = b
        while e < k and img[e, j] < level:
            e += 1
        out[j] = e
        if e > b and img[e, j] > img[e - 1, j]:
            frac[j] = (img[e, j] - level) / (img[e, j] - img[e - 1, j])
    return out, frac


@njit(cache=True, nogil=True, inline="always")
def _interp_column(img, j, x):  # pragma: no cover - numba
    """``img[:, j]`` linearly interpolated at fractional row ``x`` (clamped to the column)."""
    n = img.shape[0]
    if x <= 0.0:
        return img[0, j]
    if x >= n - 1:
        return img[n - 1, j]
    i = int(x)
    f = x - i
    return img[i, j] * (1.0 - f) + img[i + 1, j] * f


@njit(cache=True, nogil=True, inline="always")
def _interp_span(img, j, a, off, out, n_out):  # pragma: no cover - numba
    """``out[k] = _interp_column(img, j, a + (k + off))`` for ``k < n_out`` (a beam's profile at
    the integer offsets ``k + off`` from its fractional row ``a``).  Where ``0 < a + (k + off) <
    2^e`` (``a < 2^e``, the next power of two) the sum is exact - ``a`` and the integer are
    multiples of ``a``'s last place - so its row is ``floor(a) + off + k`` and its fraction ``a -
    floor(a)``: the same values ``_interp_column`` forms, without converting each position (the
    Oculus profiles of :func:`pooled_edges` 2.0 -> 1.55 ns a bin); the other bins (a sum that
    rounds, the clamped ends, a non-finite ``a``) as ``_interp_column`` does."""
    n = img.shape[0]
    k = 0
    if 0.0 < a < 2.0 ** 52:
        limit = min(n - 1.0, math.ldexp(1.0, math.frexp(a)[1]))
        fa = np.floor(a)
        f = a - fa
        g = 1.0 - f
        i0 = int(fa) + off
        while k < n_out and not a + (k + off) > 0.0:
            out[k] = img[0, j]
            k += 1
        while k < n_out and a + (k + off) < limit:
            out[k] = img[i0 + k, j] * g + img[i0 + k + 1, j] * f
            k += 1
    for q in range(k, n_out):
        out[q] = _interp_column(img, j, a + (q + off))


@njit(cache=True, nogil=True)
def surface_runs(edge, lo, hi, touch, jump=-1.0):  # pragma: no cover - numba
    """Run labels of consecutive beams whose echo intervals ``[lo, hi]`` touch (-1: no return);
    with ``jump >= 0`` also consecutive beams whose edges lie within ``jump`` bins."""
    m = edge.size
    run = np.full(m, -1, np.int64)
    r = -1
    prev = False
    for j in range(m):
        if not np.isfinite(edge[j]):
            prev = False
            continue
        if not (prev and ((lo[j] <= hi[j - 1] + touch and lo[j - 1] <= hi[j] + touch)
                          or (jump >= 0.0 and abs(edge[j] - edge[j - 1]) <= jump))):
            r += 1
        run[j] = r
        prev = True
    return run


@njit(cache=True, nogil=True)
def run_spans(run):  # pragma: no cover - numba
    """``(start, stop)`` arrays of the runs of :func:`surface_runs`' labels ``run``: beams
    ``start[k] .. stop[k] - 1`` carry one label (>= 0), in beam order."""
    m = run.size
    start = np.empty(m, np.int64)
    stop = np.empty(m, np.int64)
    k = 0
    j = 0
    while j < m:
        if run[j] < 0:
            j += 1
            continue
        j1 = j
        while j1 < m and run[j1] == run[j]:
            j1 += 1
        start[k] = j
        stop[k] = j1
        k += 1
        j = j1
    return start[:k], stop[:k]


@njit(cache=True, nogil=True, inline="always")
def _median(x, c):  # pragma: no cover - numba
    """The median of ``x[:c]`` (finite values), sorting ``x[:c]`` in place (insertion sort: the
    windows hold a few values, and np.sort allocated a copy per call)."""
    for a in range(1, c):
        v = x[a]
        b = a
        while b > 0 and x[b - 1] > v:
            x[b] = x[b - 1]
            b -= 1
        x[b] = v
    return x[c // 2] if c % 2 == 1 else 0.5 * (x[c // 2 - 1] + x[c // 2])


@njit(cache=True, nogil=True, inline="always")
def _median_of(x, lo, hi, work):  # pragma: no cover - numba
    """The median of ``x[lo:hi]`` (finite values) from a copy in the scratch ``work``
    (:func:`_median`; ``x`` is not reordered, no array allocated)."""
    for t in range(lo, hi):
        work[t - lo] = x[t]
    return _median(work, hi - lo)


@njit(cache=True, nogil=True)
def _pair_slope_median(y, x, n, work):  # pragma: no cover - numba
    """The Theil-Sen slope of the points ``(x[:n], y[:n])``: the median (:func:`_median`) of the
    ``n (n - 1) / 2`` slopes ``(y[b] - y[a]) / (x[b] - x[a])`` of their pairs ``a < b``, in ``work``."""
    nd = 0
    for a in range(n - 1):
        for b in range(a + 1, n):
            work[nd] = (y[b] - y[a]) / (x[b] - x[a])
            nd += 1
    return _median(work, nd)


@njit(cache=True, nogil=True)
def _sloped_median(win, offs, c, work, min_slope):  # pragma: no cover - numba
    """The median of the window's edges ``win[:c]`` (beams at offsets ``offs[:c]`` from the
    window's own beam) along their Theil-Sen slope ``b`` (the median of the ``c (c - 1) / 2``
    pairwise slopes, in ``work``): the median of ``win - b' offs``, the window's own beam's value
    on the robust line through them.  On a monotone slope steeper than the edges' scatter the
    plain median is the own beam's edge, its noise kept; along the line the window's beams average
    it out.  ``b' = b`` where ``|b| >= min_slope`` bins per beam, 0 below ``min_slope / 2`` (a flat
    surface's scatter makes a small slope), linear in between (no step in the alignment where a
    surface steepens).  ``min_slope <= 0``: the plain median.  ``win`` is reordered."""
    if min_slope > 0.0:
        sl = _pair_slope_median(win, offs, c, work)
        a = abs(sl)
        if a < min_slope:
            sl *= max(0.0, (a - 0.5 * min_slope) / (0.5 * min_slope))
        if sl != 0.0:
            for t in range(c):
                win[t] -= sl * offs[t]
    return _median(win, c)


@njit(cache=True, nogil=True)
def _clipped_at(clip, level, j, pos):  # pragma: no cover - numba
    """Whether either raw sample around fractional row ``pos`` of column ``j`` is clipped (``clip``
    at or above ``level``, compared in float64)."""
    n = clip.shape[0]
    i0 = int(np.floor(pos))
    for i in (i0, i0 + 1):
        if 0 <= i < n and clip[i, j] >= level:
            return True
    return False


#: The smallest pivot LAPACK's dgetf2 scales by its reciprocal (dlamch('S'), the smallest normal
#: double); below it, it divides.
_SFMIN = 2.2250738585072014e-308


@njit(cache=True, nogil=True)
def _solve_small(A, rhs, deg):  # pragma: no cover - numba
    """``np.linalg.solve(A[:deg, :deg], rhs[:deg])`` in place for ``deg`` 2 or 3 (``rhs[:deg]``
    becomes the solution, ``A[:deg, :deg]`` its LU factors) by LAPACK's operations in LAPACK's
    order - OpenBLAS' dgesv: the left-looking dgetf2 (partial pivoting, the column below a pivot
    scaled by its reciprocal), then dgetrs' row swaps and unit-lower and upper triangular solves
    (a division by each pivot), without np.linalg.solve's copies and library call.  The result is
    the same on every machine (no library in the loop); it equals np.linalg.solve's bit for bit
    where that is OpenBLAS' plain dgesv (0.3.2x on x86-64) and within its rounding elsewhere
    (OpenBLAS 0.3.31 rounds 61 % of such systems differently in the last bits; test in
    tests/ranges/test_template_edges.py).  A non-singular ``A`` (the normal equations of
    distinct positions)."""
    _lu_solve_small(A, _lu_small(A, deg), rhs, deg)


@njit(cache=True, nogil=True, inline="always")
def _lu_small(A, deg):  # pragma: no cover - numba
    """The factorisation of :func:`_solve_small` (dgetf2) in place on ``A[:deg, :deg]``: its
    pivots (a tuple of 3)."""
    piv = (0, 0, 0)
    for j in range(deg):
        # the column's earlier row swaps, its upper part (dot products), the rest (a matrix-vector
        # product subtracted as one sum)
        for i in range(j):
            p = piv[i]
            if p != i:
                t = A[i, j]
                A[i, j] = A[p, j]
                A[p, j] = t
        for i in range(1, j):
            d = 0.0
            for k in range(i):
                d += A[i, k] * A[k, j]
            A[i, j] -= d
        for r in range(j, deg):
            d = 0.0
            for k in range(j):
                d += A[r, k] * A[k, j]
            A[r, j] += -1.0 * d
        jp = j
        for r in range(j + 1, deg):
            if abs(A[r, j]) > abs(A[jp, j]):
                jp = r
        piv = _with_pivot(piv, j, jp)
        t = A[jp, j]
        if t != 0.0:
            if jp != j:
                for k in range(j + 1):
                    u = A[j, k]
                    A[j, k] = A[jp, k]
                    A[jp, k] = u
            if abs(t) >= _SFMIN:
                t = 1.0 / t
                for r in range(j + 1, deg):
                    A[r, j] *= t
            else:
                for r in range(j + 1, deg):
                    A[r, j] /= t
    return piv


@njit(cache=True, nogil=True, inline="always")
def _lu_solve_small(A, piv, rhs, deg):  # pragma: no cover - numba
    """The solve of :func:`_solve_small` (dgetrs) with the factors ``A`` and pivots ``piv`` of
    :func:`_lu_small`, in place on ``rhs[:deg]``."""
    for i in range(deg):
        p = piv[i]
        if p != i:
            t = rhs[i]
            rhs[i] = rhs[p]
            rhs[p] = t
    for i in range(deg):
        da = -rhs[i]
        for r in range(i + 1, deg):
            rhs[r] = rhs[r] + da * A[r, i]
    for i in range(deg - 1, -1, -1):
        rhs[i] = rhs[i] / A[i, i]
        da = -rhs[i]
        for r in range(i):
            rhs[r] = rhs[r] + da * A[r, i]


@njit(cache=True, nogil=True, inline="always")
def _with_pivot(piv, j, jp):  # pragma: no cover - numba
    """The pivot tuple ``piv`` with entry ``j`` set to ``jp``."""
    if j == 0:
        return (jp, piv[1], piv[2])
    if j == 1:
        return (piv[0], jp, piv[2])
    return (piv[0], piv[1], jp)


@njit(cache=True, nogil=True, inline="always")
def _box_flag(flags, h, hj, k):  # pragma: no cover - numba
    """Whether any of ``flags[k + h - hj .. k + h + hj]`` is set."""
    v = False
    for d in range(h - hj, h + hj + 1):
        v |= flags[k + d]
    return v


@njit(cache=True, nogil=True)
def _clipped_box_edge(sm, flags, h, hj, nk, p, fraction, n_own, x_first):  # pragma: no cover - numba
    """``(ok, x, level, slope, sigma)``: the ``fraction`` crossing of a Gaussian echo fitted to
    the log of the unclipped bins of profile ``sm`` (``nk`` bins) on both sides of the clipped run
    around its peak ``p`` - down to 5 % of the clipped maximum, and beyond the echo's own ``n_own``
    bins only while the profile falls - with the echo's level and rise per bin there and the
    crossing's standard error (bins, from the fit's residuals).  The crossing may lie inside the
    clipped run (an echo that peaks above twice the clip level).  Not ``ok`` with fewer than 2
    bins on either flank, a fit that does not curve down, a fitted peak not above the clipped
    maximum, a crossing before the rising flank or after the clipped run, or a rising flank that
    starts more than a bin behind ``x_first`` (the profile's first crossing of ``fraction`` x its
    clipped maximum): the clipped peak is then a deeper one than the echo's first (a strong, long
    echo clipped deep inside - the real Oculus seabed - whose Gaussian through that peak alone
    would put the edge tens of bins inside the echo).

    Bin ``k`` is clipped where :func:`_box_flag` of ``flags`` holds (the smoothing box of
    :func:`pooled_edges`: ``flags`` marks the bins where a pooled beam is clipped; ``h = hj = 0``:
    ``flags`` marks the clipped bins themselves), tested only at the bins its walks reach.  The
    walks end at the first failed test (the rising flank first, before the clipped run's end is
    sought): nearly all real Oculus fits end there (of 1283 on its 3 pings, 770 with a rising
    flank behind ``x_first``, 336 with a flank under 2 bins, 170 with a fitted peak not above the
    clipped maximum, 2 fitted), and flagging every bin of their profiles first cost more than the
    walks' own tests."""
    c0 = p
    while c0 > 0 and _box_flag(flags, h, hj, c0 - 1):
        c0 -= 1
    floor = 0.05 * sm[p]
    n_up = 0
    k = c0 - 1
    while k >= 0 and not _box_flag(flags, h, hj, k) and sm[k] >= floor:
        n_up += 1
        k -= 1
    first = k + 1
    if n_up < 2 or first - 1.0 > x_first:
        return False, 0.0, 0.0, 0.0, 0.0
    c1 = p
    while c1 < nk - 1 and _box_flag(flags, h, hj, c1 + 1):
        c1 += 1
    n_down = 0
    k = c1 + 1
    while k < nk and not _box_flag(flags, h, hj, k) and sm[k] >= floor and (k < n_own or sm[k] < sm[k - 1]):
        n_down += 1
        k += 1
    if n_down < 2:
        return False, 0.0, 0.0, 0.0, 0.0
    return _clipped_fit(sm, p, c0, c1, first, n_down, fraction)


@njit(cache=True, nogil=True)
def _clipped_fit(sm, p, c0, c1, first, n_down, fraction):  # pragma: no cover - numba
    """The fit of :func:`_clipped_box_edge` to the bins ``first .. c1 + n_down`` of ``sm`` outside the
    clipped run ``c0 .. c1`` around its peak ``p``: its result."""
    # sums for the least-squares parabola in k - c0 (centred for conditioning)
    S = np.zeros(5)
    T = np.zeros(3)
    for k in range(first, c1 + 1 + n_down):
        if c0 <= k <= c1:
            continue
        u = float(k - c0)
        y = np.log(sm[k])
        up = 1.0
        for e in range(5):
            S[e] += up
            if e < 3:
                T[e] += up * y
            up *= u
    A = np.empty((3, 3))
    for r in range(3):
        for q in range(3):
            A[r, q] = S[r + q]
    lu = A.copy()
    _solve_small(lu, T, 3)  # np.linalg.solve(A, T) into T
    a, b, c = T[0], T[1], T[2]
    if not c < 0:
        return False, 0.0, 0.0, 0.0, 0.0
    u0 = -b / (2.0 * c)
    w2 = -1.0 / (2.0 * c)
    peak = np.exp(a + b * u0 + c * u0 * u0)
    if not peak > sm[p] or not np.isfinite(peak):
        return False, 0.0, 0.0, 0.0, 0.0
    du = np.sqrt(-2.0 * np.log(fraction) * w2)
    x = c0 + u0 - du
    if not (first - 1.0 <= x <= c1):
        return False, 0.0, 0.0, 0.0, 0.0
    # standard error of the crossing: the fit's residual variance through the covariance of
    # (a, b, c) and the crossing's gradient u0 - du = -b / 2c - sqrt(ln(f) / c)
    rss = 0.0
    n = 0
    for k in range(first, c1 + 1 + n_down):
        if c0 <= k <= c1:
            continue
        u = float(k - c0)
        r = np.log(sm[k]) - (a + b * u + c * u * u)
        rss += r * r
        n += 1
    cov = np.linalg.inv(A) * (rss / max(n - 3, 1))
    lf = np.log(fraction)
    g1 = -1.0 / (2.0 * c)
    g2 = b / (2.0 * c * c) + (lf / (c * c)) / (2.0 * np.sqrt(lf / c))
    var = g1 * g1 * cov[1, 1] + 2.0 * g1 * g2 * cov[1, 2] + g2 * g2 * cov[2, 2]
    level = fraction * peak
    return True, x, level, level * du / w2, np.sqrt(max(var, 0.0))


@njit(cache=True, nogil=True)
def _profile_needs(run, count, depth, half_beams, extra):  # pragma: no cover - numba
    """Per beam ``jj`` of :func:`pooled_edges`, how many profile bins of beams ``0 .. jj`` the
    windows read through the running sums ``csum[jj + 1]``: the most, over the windows (beams
    ``j`` with ``count[j] >= 3``, the ``count[j]`` beams of ``j``'s run from the first within
    ``half_beams`` of it) ending after ``jj``, of ``depth[j] + extra`` (the bins
    ``front + depth + 1 + tail`` of the profile plus the smoothing's ``2 h``)."""
    m = run.size
    need = np.zeros(m, np.int64)
    for j in range(m):
        if count[j] < 3:
            continue
        lo = max(0, j - half_beams)
        while run[lo] != run[j]:
            lo += 1
        hi = lo + count[j]
        need[hi - 1] = max(need[hi - 1], depth[j] + extra)
    for jj in range(m - 2, -1, -1):
        need[jj] = max(need[jj], need[jj + 1])
    return need


@njit(cache=True, nogil=True)
def _clipped_rows(clip, level):  # pragma: no cover - numba
    """``(first, rows)``: the rows of the samples of ``clip`` at or above ``level`` (compared in
    float64) by column, ascending: ``rows[first[j]:first[j + 1]]`` for column ``j``.  One pass
    along the rows (a row without one costs a vectorised test) instead of walks down the columns
    (the real Oculus: ~1500 clipped samples a ping, 87 k column reads a :func:`pooled_edges`
    call); :func:`first_clipped_rows` lists a span of rows with it."""
    n, m = clip.shape
    first = np.zeros(m + 1, np.int64)
    hit = np.empty(n, np.int64)
    n_hit = 0
    for i in range(n):
        row = clip[i]
        some = False
        for j in range(m):
            some |= row[j] >= level
        if some:
            hit[n_hit] = i
            n_hit += 1
            for j in range(m):
                first[j + 1] += row[j] >= level
    for j in range(m):
        first[j + 1] += first[j]
    rows = np.empty(first[m], np.int64)
    fill = first[:m].copy()
    for t in range(n_hit):
        row = clip[hit[t]]
        for j in range(m):
            if row[j] >= level:
                rows[fill[j]] = hit[t]
                fill[j] += 1
    return first, rows


@njit(cache=True, nogil=True)
def _clipped_bins(clip, level, j, rows, a, off, n_read, out, n_out):  # pragma: no cover - numba
    """The bins ``k < n_read`` whose test ``_clipped_at(clip, level, j, a + (k + off))`` holds,
    ascending, written to ``out`` from ``out[n_out]`` on (the clipped profile bins of beam ``j`` in
    :func:`pooled_edges`); returns the index past the last.  ``rows``: the clipped rows of column
    ``j``, ascending (:func:`_clipped_rows`).  ``floor(a + (k + off))`` is ``floor(a) + off + k``
    or the next row (a rounded sum) and does not decrease with ``k``: of the clipped rows from
    the first test's row to the last test's next row, only the up to 3 bins whose tests can read
    each are tested, without reading the column (the real Oculus, clipped in most columns, has
    ~6 clipped samples in reach of a column's ~170 bins: 7 k tests a call instead of 88 k)."""
    n = clip.shape[0]
    if n_read > 0 and not abs(a) < 2.0 ** 52:  # (NaN: every test fails, as it reads no row)
        for k in range(n_read):
            if _clipped_at(clip, level, j, a + (k + off)):
                out[n_out] = k
                n_out += 1
        return n_out
    if n_read <= 0 or rows.size == 0:
        return n_out
    r0 = min(max(int(np.floor(a + off)), 0), n)
    r1 = min(max(int(np.floor(a + (n_read - 1 + off))) + 2, 0), n)
    f0 = int(np.floor(a)) + off
    last = -1  # the last bin found
    for i in rows:
        if i < r0:
            continue
        if i >= r1:
            break
        # a bin whose test reads row i (the column is not read); one found by an earlier row
        # is not after this row's (its test's rows are not after this row's)
        for k in range(max(i - f0 - 2, last + 1), min(i - f0 + 1, n_read)):
            i0 = int(np.floor(a + (k + off)))
            if i0 == i or i0 + 1 == i:
                out[n_out] = k
                n_out += 1
                last = k
    return n_out


@njit(cache=True, nogil=True, inline="always")
def _mark_bins(flags, bins, t0, t1, value):  # pragma: no cover - numba
    """``flags[bins[t0:t1]] = value``."""
    for t in range(t0, t1):
        flags[bins[t]] = value


#: The rising flank :func:`_flank_line` fits: its samples between these fractions of the peak.
FLANK_LOW = 0.2
FLANK_HIGH = 0.8


@njit(cache=True, nogil=True)
def _flank_line(sm, i, lv, lo, p, w):  # pragma: no cover - numba
    """The crossing of ``lv`` (x, bins from ``lo``) and the rise per bin of the least-squares line
    through the rising flank of ``sm`` around its first crossing ``sm[i - 1] < lv <= sm[i]``:
    the samples from ``i - 1`` back while at least ``FLANK_LOW`` x the peak ``sm[p]`` and from
    ``i`` on while at most ``FLANK_HIGH`` x the peak (the flank between 20 % and 80 % of it), at
    most ``w`` on either side of the crossing and within ``lo .. p``.
    ``(0.0, -1.0)`` when fewer than 3 samples lie there or the line does not rise."""
    a = i - 1
    while a - 1 >= max(lo, i - w) and sm[a - 1] >= FLANK_LOW * sm[p]:
        a -= 1
    b = i
    while b + 1 <= min(p, i - 1 + w) and sm[b + 1] <= FLANK_HIGH * sm[p]:
        b += 1
    if b - a + 1 < 3:
        return 0.0, -1.0
    n = 0.0
    sx = 0.0
    sy = 0.0
    sxx = 0.0
    sxy = 0.0
    for k in range(a, b + 1):
        x = float(k - lo)
        n += 1.0
        sx += x
        sy += sm[k]
        sxx += x * x
        sxy += x * sm[k]
    den = n * sxx - sx * sx
    sl = (n * sxy - sx * sy) / den
    if not sl > 0.0:
        return 0.0, -1.0
    return (lv - (sy - sl * sx) / n) / sl, sl


@njit(cache=True, nogil=True)
def _peak_level(sm, p, lo, hi, w, A, T):  # pragma: no cover - numba
    """The height of the first peak ``p`` of profile ``sm``: the maximum over the window of the
    least-squares parabola through ``sm[p - w .. p + w]`` (within ``lo .. hi - 1``; its value at
    ``p`` where it has no maximum), at most ``sm[p]``; ``sm[p]`` itself with ``w = 0``, fewer
    than 3 samples or a height that is not positive.  The largest of noisy samples lies above the
    echo's own peak (it is the sample the noise raised most), and with it the level ``fraction``
    x peak and the crossing lie above and behind the echo's; a parabola through the samples
    around it averages that noise while following a peaked echo's curvature.  ``A`` (3, 3) and
    ``T`` (3,): scratch."""
    if w <= 0:
        return sm[p]
    a = max(lo, p - w)
    b = min(hi - 1, p + w)
    if b - a < 2:
        return sm[p]
    # the normal equations in u = k - p from the power sums, as _clipped_fit's
    s0 = s1 = s2 = s3 = s4 = 0.0
    T[:] = 0.0
    for k in range(a, b + 1):
        u = float(k - p)
        y = sm[k]
        s0 += 1.0
        s1 += u
        s2 += u * u
        s3 += u * u * u
        s4 += u * u * u * u
        T[0] += y
        T[1] += u * y
        T[2] += u * u * y
    A[0, 0], A[0, 1], A[0, 2] = s0, s1, s2
    A[1, 0], A[1, 1], A[1, 2] = s1, s2, s3
    A[2, 0], A[2, 1], A[2, 2] = s2, s3, s4
    _solve_small(A, T, 3)  # T = (c0, c1, c2) of c0 + c1 u + c2 u^2
    c0, c1, c2 = T[0], T[1], T[2]
    u0 = 0.0  # a parabola without a maximum: its value at p
    if c2 < 0.0:
        u0 = min(max(-c1 / (2.0 * c2), float(a - p)), float(b - p))
    v = c0 + c1 * u0 + c2 * u0 * u0
    return min(v, sm[p]) if v > 0.0 else sm[p]


@njit(cache=True, nogil=True)
def pooled_edges(img, edge, stop, run, half_beams, front_bins, max_bins, smooth_bins, fraction, n_iter,
                 clip, clip_level, fit_front_bins, forward, flank_bins, peak_bins,
                 min_slope):  # pragma: no cover - numba
    """Leading edges measured on the surface-aligned mean profile of neighbouring beams
    (see :func:`sonarmap.ranges.echoes.pooled_edges`).

    ``edge`` (fractional bins, NaN: no return) and ``stop`` (one past the echo's last structure
    bin) per beam; ``run`` labels the runs of beams that are one surface (-1: none).  Returns per
    beam the new edge, the pooled profile's value and rise per bin at the crossing, the number of
    beams pooled (0 where the beam keeps its own edge), the standard error of the pooled
    profile at the crossing and whether the edge is that of a fitted clipped echo.

    A raw sample is at the receiver's full scale where ``clip`` (the image's shape; shape (0, 0):
    none) is at or above ``clip_level`` (compared in float64): a 0/1 mask with level 1, or the
    raw image itself with its full-scale level (no mask to form: only the samples the profiles
    reach are read).  Where the pooled profile's peak is clipped, its first peak is the clip
    level, below the echo's own: the leading edge is then the half-peak crossing of a Gaussian
    echo fitted to the log of the unclipped samples on both flanks (:func:`_clipped_box_edge`), whose
    rising flank may reach ``fit_front_bins`` (>= ``front_bins``) in front of the alignment.  The
    peak search and the half-peak walk of unclipped profiles stay within ``front_bins``.

    With ``forward`` the crossing is the first bin from the profile's front that reaches the level
    (the first crossing); else the walk from the peak towards the sonar to the first bin below it
    (which stops at a dip inside a deep echo, behind its front).  With ``flank_bins`` > 0 an
    unclipped crossing is that of the line through the profile's rising flank around it
    (:func:`_flank_line`, at most ``flank_bins`` samples either side) rather than of the two
    samples around it, where that line rises and crosses within that window.  The level is
    ``fraction`` x the peak's height of :func:`_peak_level` with ``peak_bins``.  The alignment is
    the running median of the current edges, along the window's slope from ``min_slope / 2`` bins
    per beam, fully from ``min_slope`` (:func:`_sloped_median`; ``min_slope <= 0``: the plain
    median).
    """
    m = edge.size
    cur = edge.copy()
    has_clip = clip.shape[0] > 0
    # the profile's front: the fitted rising flank of a clipped echo may start further in front
    front = max(front_bins, fit_front_bins) if has_clip else front_bins
    lim = front - front_bins
    fitted = np.zeros(m, np.bool_)
    value = np.full(m, np.nan)
    rise = np.full(m, np.nan)
    used = np.zeros(m, np.int64)
    noise = np.full(m, np.nan)
    h = smooth_bins // 2
    win = np.empty(2 * half_beams + 1)
    offs = np.empty(2 * half_beams + 1)
    pair = np.empty((2 * half_beams + 1) * half_beams)
    align = np.empty(m)
    depth = np.zeros(m, np.int64)
    count = np.zeros(m, np.int64)
    crow0, crows = _clipped_rows(clip, clip_level)
    pA = np.empty((3, 3))
    pT = np.empty(3)
    for _ in range(n_iter):
        # the alignment: running median of the current edges within each run
        for j in range(m):
            align[j] = cur[j]
            count[j] = 0
            if run[j] < 0:
                continue
            c = 0
            for jj in range(max(0, j - half_beams), min(m, j + half_beams + 1)):
                if run[jj] == run[j]:
                    win[c] = cur[jj]
                    offs[c] = jj - j
                    c += 1
            count[j] = c
            if c >= 3:
                align[j] = _sloped_median(win, offs, c, pair, min_slope)
        # the window's echo depth behind the alignment (median, 3 .. max_bins bins)
        kmax = 0
        for j in range(m):
            if count[j] < 3:
                continue
            c = 0
            for jj in range(max(0, j - half_beams), min(m, j + half_beams + 1)):
                if run[jj] == run[j]:
                    win[c] = stop[jj] - align[jj]
                    c += 1
            depth[j] = int(min(max(_median(win, c), 3.0), max_bins))
            kmax = max(kmax, depth[j])
        # (with clipping, front_bins more behind the echo: the falling flank of a clipped peak)
        tail = front_bins if has_clip else 0
        width = front + kmax + 1 + 2 * h + tail
        # every beam's own profile at offsets -front - h .. kmax + h from its alignment, and
        # their running sum over beams (a run is a contiguous block of beams: a window's sum is
        # a difference of two rows)
        # (beam jj's profile and running sums only as far as a window ending past it reads them:
        # the same values where read; a few deep echoes no longer widen every beam's profile)
        need = _profile_needs(run, count, depth, half_beams, front + 1 + tail + 2 * h)
        # (not zeroed: only the bins below need are read; a beam in no run, its profile 0, copies
        # the running sums, which are never -0.0; 2 x 390 kB zeroed per Oculus iteration)
        prof = np.empty((m, width))
        csum = np.empty((m + 1, width))
        csum[0] = 0.0
        # (with clipping, the clipped profile bins of beam jj: cbins[cfirst[jj]:cfirst[jj + 1]])
        cfirst = np.zeros(m + 1, np.int64)
        cbins = np.empty(need.sum() if has_clip else 0, np.int64)
        for jj in range(m):
            if run[jj] >= 0:
                _interp_span(img, jj, align[jj], -h - front, prof[jj], need[jj])
                for k in range(need[jj]):
                    csum[jj + 1, k] = csum[jj, k] + prof[jj, k]
            else:
                csum[jj + 1, :need[jj]] = csum[jj, :need[jj]]
            if has_clip:
                cfirst[jj + 1] = _clipped_bins(clip, clip_level, jj, crows[crow0[jj]:crow0[jj + 1]], align[jj],
                                               -h - front, need[jj] if run[jj] >= 0 else 0, cbins, cfirst[jj])
        any_k = np.zeros(width, np.bool_)
        new = cur.copy()
        mean = np.empty(width)
        sm = np.empty(width)
        for j in range(m):
            c = count[j]
            if c < 3:
                continue
            lo = max(0, j - half_beams)
            while run[lo] != run[j]:
                lo += 1
            hi = lo + c
            nk = front + depth[j] + 1
            nf = nk + tail
            row_hi = csum[hi]
            row_lo = csum[lo]
            cf = float(c)
            for k in range(nf + 2 * h):
                mean[k] = (row_hi[k] - row_lo[k]) / cf
            # smoothed along range over smooth_bins (the profile extends h bins either side), only
            # where the echo is deep enough (>= 6 smoothing half-widths) for the box not to widen
            # it: a one-bin echo smoothed over 3 bins would have its crossing a bin early
            hj = h if depth[j] >= 6 * h else 0
            # (the box summed from 0 in order, the 3-bin and 1-bin boxes written out: their loops
            # vectorise, the loop over the box did not; 1024 x 512 pings 3.0 -> 2.6 ms)
            if hj == 1:
                for k in range(nf):
                    sm[k] = (((0.0 + mean[k + h - 1]) + mean[k + h]) + mean[k + h + 1]) / 3.0
            elif hj == 0:
                for k in range(nf):
                    sm[k] = (0.0 + mean[k + h]) / 1.0
            else:
                for k in range(nf):
                    acc = 0.0
                    for d in range(h - hj, h + hj + 1):
                        acc += mean[k + d]
                    sm[k] = acc / (2 * hj + 1)
            # peak and walk within front_bins of the alignment (profile bins lim ..)
            p = lim
            for k in range(lim + 1, nk):
                if sm[k] > sm[p]:
                    p = k
            if not sm[p] > 0:
                continue
            # (the parabola only where the echo is deep enough, >= 6 of its half-widths, to be
            # parabolic over it, as the box above: a shallow echo peaks like the pulse, which a
            # 5-bin parabola reads low - the simulated surveys' hull and seafloor, under 12 bins)
            lv = fraction * _peak_level(sm, p, lim, nk, peak_bins if depth[j] >= 6 * peak_bins else 0, pA, pT)
            if forward:  # the first crossing from the front (i <= p: sm[p] reaches the level)
                i = lim
                while i < p and sm[i] < lv:
                    i += 1
            else:  # the walk back from the peak
                i = p
                while i > lim and sm[i - 1] >= lv:
                    i -= 1
            # x: the crossing in bins from the profile's bin lim (front_bins in front of the
            # alignment)
            if i == lim:
                x = 0.0
                slope = sm[lim + 1] - sm[lim] if nk > lim + 1 else 0.0
            else:
                slope = sm[i] - sm[i - 1]
                x = (i - 1 - lim) + (lv - sm[i - 1]) / max(slope, 1e-12)
                if flank_bins > 0:
                    # the line through the rising flank (20-80 % of the peak) around the
                    # crossing: the crossing of a slow, speckled rise from all its samples
                    xf, sf = _flank_line(sm, i, lv, lim, p, flank_bins)
                    if sf > 0.0 and i - 1 - flank_bins - lim <= xf <= i + flank_bins - lim:
                        x = xf
                        slope = sf
            if has_clip:
                fitted[j] = False
                fit_sx = 0.0
                # a smoothed bin is clipped when any pooled beam has a clipped sample in its box
                # (the other bins' flags only for a clipped peak: the fit reads them)
                _mark_bins(any_k, cbins, cfirst[lo], cfirst[hi], True)
                if _box_flag(any_k, h, hj, p):
                    ok, xf, lvf, sf, fit_sx = _clipped_box_edge(sm, any_k, h, hj, nf, p, fraction, nk, lim + x)
                    if ok:
                        x, lv, slope = xf - lim, lvf, sf
                        fitted[j] = True
                _mark_bins(any_k, cbins, cfirst[lo], cfirst[hi], False)
            new[j] = align[j] + x - front_bins
            value[j] = lv
            rise[j] = slope
            used[j] = c
            # the mean profile's own noise at the crossing: the spread of the pooled beams'
            # smoothed values there, over sqrt(beams) - speckle and misalignment alike
            i0 = max(int(np.floor(x)), -lim)
            f = x - i0
            s1 = 0.0
            s2 = 0.0
            for jj in range(lo, hi):
                v0 = 0.0
                v1 = 0.0
                for d in range(h - hj, h + hj + 1):
                    v0 += prof[jj, lim + i0 + d]
                    v1 += prof[jj, min(lim + i0 + 1, nk - 1) + d]
                v = ((1.0 - f) * v0 + f * v1) / (2 * hj + 1)
                s1 += v
                s2 += v * v
            var = max(s2 / c - (s1 / c) ** 2, 0.0) * c / (c - 1)
            noise[j] = np.sqrt(var / c)
            if fitted[j]:
                # the fitted crossing's standard error (bins) as a profile noise at its rise: the
                # sigma then scales it as it scales the pooled profile's own jitter
                noise[j] = fit_sx * slope
        cur = new
    return cur, value, rise, used, noise, fitted


@njit(cache=True, nogil=True)
def _window_llr(levels, lut, j, t, thick):  # pragma: no cover - numba
    acc = 0.0
    for i in range(t, t + thick):
        acc += lut[levels[i, j]]
    return acc


@njit(cache=True, nogil=True)
def _best_window(levels, lut, j, a, b, thick):  # pragma: no cover - numba
    """The start ``t`` in ``a .. b`` of beam ``j``'s ``thick``-bin window of largest summed
    log-likelihood ratio, and that sum (``-inf`` when ``b < a``)."""
    best = -np.inf
    t_best = a
    for t in range(a, b + 1):
        v = _window_llr(levels, lut, j, t, thick)
        if v > best:
            best = v
            t_best = t
    return t_best, best


@njit(cache=True, nogil=True, inline="always")
def _mark_window(out, j, t, thick, col_lo, col_hi):  # pragma: no cover - numba
    """Mark beam ``j``'s window ``t .. t + thick - 1`` in ``out`` and grow the column's rows
    ``col_lo[j] .. col_hi[j] - 1`` to cover it."""
    for i in range(t, t + thick):
        out[i, j] = True
    col_lo[j] = min(col_lo[j], t)
    col_hi[j] = max(col_hi[j], t + thick)


@njit(cache=True, nogil=True)
def _continue_run(levels, lut, edge, j0, d, direction, thick, max_beams, window_bins, min_evidence, max_misses,
                  out, col_lo, col_hi):  # pragma: no cover - numba
    """One walk of :func:`continuation_mask` from the run's end beam ``j0`` in ``direction`` along
    the slope ``d`` (bins per beam of walk); marks its windows (:func:`_mark_window`).  A beam
    missed between two found ones is searched again around the line between them (a tighter
    prediction than the extrapolation that missed it)."""
    n, m = levels.shape
    e0 = edge[j0]
    j = j0
    misses = 0
    for _ in range(max_beams):
        j += direction
        if j < 0 or j >= m:
            break
        steps = abs(j - j0)
        pred = e0 + d * steps
        w = max(window_bins, 0.5 * thick) + steps
        if np.isfinite(edge[j]) and abs(edge[j] - pred) <= w + thick:
            break  # the tracker links an existing return
        a = int(max(np.floor(pred - w), 0.0))
        b = int(min(np.ceil(pred + w), n - thick))
        if b < a:
            break
        t_best, best = _best_window(levels, lut, j, a, b, thick)
        if best >= min_evidence:
            _mark_window(out, j, t_best, thick, col_lo, col_hi)
            # the beams missed since the last one found, around the line between the two
            wm = max(window_bins, 0.5 * thick)
            for k in range(1, steps):
                jm = j0 + direction * k
                pm = e0 + (t_best - e0) * k / steps
                tm, bm = _best_window(levels, lut, jm, int(max(np.floor(pm - wm), 0.0)),
                                      int(min(np.ceil(pm + wm), n - thick)), thick)
                if bm >= min_evidence:
                    _mark_window(out, jm, tm, thick, col_lo, col_hi)
            e0 = float(t_best)
            j0 = j
            misses = 0
            continue
        misses += 1
        if misses > max_misses:
            break


@njit(cache=True, nogil=True)
def continuation_mask(levels, lut, edge, stop, run, min_run, max_beams, window_bins, min_evidence, max_misses):  # pragma: no cover - numba
    """Continuation pixels of tracked surfaces (see :func:`sonarmap.ranges.tracking.continuation_mask`);
    ``lut[levels]`` is the per-pixel log-likelihood ratio; also the first and one-past-last row
    holding one (``(n, 0)``: none), overall and per column (``col_lo``, ``col_hi``)."""
    n, m = levels.shape
    out = np.zeros((n, m), np.bool_)
    col_lo = np.full(m, n, np.int64)
    col_hi = np.zeros(m, np.int64)
    n_runs = run.max() + 1
    tail = np.empty(10, np.int64)
    tail_edge = np.empty(10)
    slopes = np.empty(45)
    depth = np.empty(m)
    for r in range(n_runs):
        b0 = -1
        b1 = -1
        for j in range(m):
            if run[j] == r:
                if b0 < 0:
                    b0 = j
                b1 = j
        if b0 < 0 or b1 - b0 + 1 < min_run:
            continue
        c = 0
        for j in range(b0, b1 + 1):
            depth[c] = stop[j] - edge[j]
            c += 1
        s = np.sort(depth[:c])
        med = s[c // 2] if c % 2 == 1 else 0.5 * (s[c // 2 - 1] + s[c // 2])
        thick = int(min(max(med, 2.0), 16.0))
        for direction in (-1, 1):
            nt = min(10, b1 - b0 + 1)
            for q in range(nt):
                tail[q] = b1 - q if direction > 0 else b0 + q
            # Theil-Sen slope of the edge over the run's last beams, per beam in the walk's direction
            for q in range(nt):
                tail_edge[q] = edge[tail[q]]
            d = _pair_slope_median(tail_edge, tail, nt, slopes) * direction
            _continue_run(levels, lut, edge, tail[0], d, direction, thick, max_beams, window_bins, min_evidence,
                          max_misses, out, col_lo, col_hi)
    # the overall rows: the columns' (n, 0 when no column has one)
    return out, col_lo.min() if m else n, col_hi.max() if m else 0, col_lo, col_hi


@njit(cache=True, nogil=True)
def continuation_extra(extra, cand, first, edge_bin, col_lo, col_hi):  # pragma: no cover - numba
    """The continuation pixels of :func:`sonarmap.ranges.measure.surface_ranges`: ``extra & ~cand``
    on the beams whose first such pixel lies in front of the beam's return (``edge_bin[first[j]]``;
    every beam without one), written into ``extra`` (whose pixels of column ``j`` all lie on rows
    ``col_lo[j] .. col_hi[j] - 1``, :func:`continuation_mask`); whether any is left, those beams
    (ascending) and the first and one-past-last row holding such a pixel (``(n, 0)``: none).
    Only those rows of each column are read (a walk over every row of the span that the
    continuations cover read whole rows of both masks for a few pixels: 4096 x 512 simulated
    pings 0.6 ms)."""
    n, m = extra.shape
    top = np.full(m, n, np.int64)
    for j in range(m):
        for i in range(max(col_lo[j], 0), min(col_hi[j], n)):
            if extra[i, j]:
                if cand[i, j]:
                    extra[i, j] = False
                elif top[j] == n:
                    top[j] = i
    keep = np.zeros(m, np.bool_)
    hit = False
    for j in range(m):
        keep[j] = top[j] < n and (first[j] < 0 or top[j] < edge_bin[first[j]])
        hit = hit or keep[j]
    e0 = n
    e1 = 0
    if hit:
        for j in range(m):
            for i in range(max(col_lo[j], 0), min(col_hi[j], n)):
                if extra[i, j]:
                    if not keep[j]:
                        extra[i, j] = False
                    else:
                        e0 = min(e0, i)
                        e1 = max(e1, i + 1)
    return extra, hit, np.flatnonzero(keep), e0, e1


@njit(cache=True, nogil=True)
def continuation_pixels(sel, edge_bin, start_bin, stop_bin, touch, levels, lut, min_run, max_beams, window_bins,
                        min_evidence, max_misses, cand):  # pragma: no cover - numba
    """:func:`first_interval_runs` of the returns ``sel``, :func:`continuation_mask` of its runs
    and :func:`continuation_extra` of that mask against ``cand`` (the returns' edges ``edge_bin``)
    in one call: ``(hit, extra, beams, r0, r1)`` as :func:`continuation_extra` gives them, ``hit``
    False without a continuation pixel at all."""
    edge, stop, run = first_interval_runs(sel, edge_bin, start_bin, stop_bin, touch, -1.0)
    out, r0, r1, col_lo, col_hi = continuation_mask(levels, lut, edge, stop, run, min_run, max_beams, window_bins,
                                                    min_evidence, max_misses)
    if r1 <= r0:
        return False, out, np.zeros(0, np.int64), r0, r1
    extra, hit, cols, e0, e1 = continuation_extra(out, cand, sel, edge_bin, col_lo, col_hi)
    return hit, extra, cols, e0, e1


@njit(cache=True, nogil=True, inline="always")
def _grow_rows(row, i, r0, r1, n):  # pragma: no cover - numba
    """``(r0, r1)``, the first and one-past-last row holding a true pixel (``r0 == n``: none yet),
    after row ``i`` (``row``: whether it holds one)."""
    if row:
        if r0 == n:
            r0 = i
        r1 = i + 1
    return r0, r1


@njit(cache=True, nogil=True)
def union_extent(a, b):  # pragma: no cover - numba
    """``(a | b, r0, r1)`` of two C-contiguous boolean images of one shape: their union and the
    first and one-past-last row holding a true pixel of it (``(n, 0)``: none), in one pass."""
    n, m = a.shape
    out = np.empty((n, m), np.bool_)
    fa = a.reshape(n * m).view(np.uint8)
    fb = b.reshape(n * m).view(np.uint8)
    fo = out.reshape(n * m).view(np.uint8)
    r0 = n
    r1 = 0
    for i in range(n):
        base = i * m
        row = np.uint8(0)
        for j in range(m):
            v = fa[base + j] | fb[base + j]
            fo[base + j] = v
            row |= v
        r0, r1 = _grow_rows(row, i, r0, r1, n)
    return out, r0, r1


@njit(cache=True, nogil=True)
def mask_extent(mask):  # pragma: no cover - numba
    """``(r0, r1, n_cols)`` of a C-contiguous boolean image: the first and one-past-last row
    holding a true pixel (``(n, 0)``: none) and the number of columns holding one; one pass
    (numpy's ``any`` along the short axis of a tall image was slower than the rest of the step)."""
    n, m = mask.shape
    flat = mask.reshape(n * m).view(np.uint8)
    acc = np.zeros(m, np.uint8)
    r0 = n
    r1 = 0
    for i in range(n):
        base = i * m
        row = np.uint8(0)
        for j in range(m):
            v = flat[base + j]
            acc[j] |= v
            row |= v
        r0, r1 = _grow_rows(row, i, r0, r1, n)
    n_cols = 0
    for j in range(m):
        if acc[j]:
            n_cols += 1
    return r0, r1, n_cols


@njit(cache=True, nogil=True)
def smooth_rows(img, size):  # pragma: no cover - numba
    """``scipy.ndimage.uniform_filter1d(img, size, axis=0, mode="nearest")`` of a 2-D float64 image,
    bit for bit (scipy's arithmetic: each column extended by its edge values, ``size // 2`` before,
    a double running sum ``+= new - old`` divided by the size), over whole rows at a time (one
    running sum per column: the same operations in the same order, on contiguous memory)."""
    h, w = img.shape
    out = np.empty((h, w))
    b = size // 2
    tmp = np.zeros(w)
    for k in range(size):
        t = min(max(k - b, 0), h - 1)
        for j in range(w):
            tmp[j] += img[t, j]
    for j in range(w):
        out[0, j] = tmp[j] / size
    for k in range(1, h):
        t_new = min(k + size - 1 - b, h - 1)
        t_old = max(k - 1 - b, 0)
        for j in range(w):
            tmp[j] += img[t_new, j] - img[t_old, j]
            out[k, j] = tmp[j] / size
    return out


# ------------------------------------------------------------------ band pooling (candidates)
@njit(cache=True, nogil=True)
def box_mean_f32(img, size0, size1):  # pragma: no cover - numba
    """``scipy.ndimage.uniform_filter(img, size=(size0, size1), mode="constant")`` of a 2-D float32
    image, bit for bit (scipy's arithmetic: axis 0 then axis 1, axes of size 1 skipped, each line
    zero-padded by ``size // 2`` before, a double running sum ``+= new - old`` divided by the size
    and rounded to float32; ``tests/test_pipeline.py`` checks the identity against scipy).

    The pass along axis 0 runs over whole rows (one running sum per column, the same operations
    in the same order as a column at a time, on contiguous memory)."""
    h, w = img.shape
    mid = np.empty((h, w), dtype=np.float32)
    if size0 > 1:
        b = size0 // 2
        tmp = np.zeros(w)
        for k in range(size0):
            t = k - b
            for j in range(w):
                tmp[j] += float(img[t, j]) if 0 <= t < h else 0.0
        for j in range(w):
            mid[0, j] = tmp[j] / size0
        for k in range(1, h):
            t_new = k + size0 - 1 - b
            t_old = k - 1 - b
            for j in range(w):
                vn = float(img[t_new, j]) if t_new < h else 0.0
                vo = float(img[t_old, j]) if t_old >= 0 else 0.0
                tmp[j] += vn - vo
                mid[k, j] = tmp[j] / size0
    else:
        mid[:, :] = img
    if size1 <= 1:
        return mid
    out = np.empty((h, w), dtype=np.float32)
    buf = np.zeros(w + size1 - 1)
    for i in range(h):
        _box_line(mid[i, :], buf, size1, out[i, :])
    return out


@njit(cache=True, nogil=True)
def box_band(img, size0, size1, level):  # pragma: no cover - numba
    """``box_mean_f32(img, size0, size1) >= level`` (``level`` float32: numpy compares a float32
    image with a Python float in float32), with the first and one-past-last row holding a band
    pixel and the number of columns holding one (0 rows when none).

    For a positive finite ``level`` the pass along axis 1 compares each running sum with
    :func:`_mean_threshold` instead of dividing, rounding and comparing (the same test: it is
    monotone in the sum), 4 rows side by side (:func:`_box_rows_band`)."""
    # (np.int64(1): the literal would compile box_mean_f32 once more for each Literal[int] call)
    mid = box_mean_f32(img, size0, np.int64(1))
    h, w = mid.shape
    if size1 > 1 and 0 < level < np.inf:
        band = _box_rows_band(mid, size1, _mean_threshold(level, size1))
    else:
        band = (box_mean_f32(mid, np.int64(1), size1) if size1 > 1 else mid) >= level
    col = np.zeros(w, dtype=np.bool_)
    r0 = h
    r1 = 0
    for i in range(h):
        row = False
        for j in range(w):
            v = band[i, j]
            col[j] |= v
            row |= v
        if row:
            if r0 == h:
                r0 = i
            r1 = i + 1
    n_cols = 0
    for j in range(w):
        if col[j]:
            n_cols += 1
    return band, r0, r1, n_cols


@njit(cache=True, nogil=True)
def _mean_threshold(level, size):  # pragma: no cover - numba
    """The least float64 ``x`` with ``float32(x / size) >= level`` (``level`` a positive finite
    float32): the test is monotone in ``x`` (a correctly rounded division, then a rounding), so it
    is ``x >= threshold``; found by bisection over the bit patterns of the positive doubles."""
    bits = np.empty(1, np.int64)
    lo = 0  # +0.0 fails the test
    hi = 0x7FF0000000000000  # +inf passes it
    while hi - lo > 1:
        mid = lo + (hi - lo) // 2
        bits[0] = mid
        if np.float32(bits.view(np.float64)[0] / size) >= level:
            hi = mid
        else:
            lo = mid
    bits[0] = hi
    return bits.view(np.float64)[0]


@njit(cache=True, nogil=True)
def _box_rows_band(mid, size, threshold):  # pragma: no cover - numba
    """``box_mean_f32(mid, 1, size) >= level`` for ``threshold = _mean_threshold(level, size)``:
    per row the running sum of :func:`_box_line` (the same operations in the same order: bit for
    bit) compared with the threshold; 4 rows side by side (a row's running sum is a chain of
    dependent additions), the rows left over one at a time."""
    h, w = mid.shape
    band = np.empty((h, w), dtype=np.bool_)
    b = size // 2
    for i in range(0, h - h % 4, 4):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        for k in range(size):
            t = k - b
            if 0 <= t < w:
                a0 += float(mid[i, t])
                a1 += float(mid[i + 1, t])
                a2 += float(mid[i + 2, t])
                a3 += float(mid[i + 3, t])
            else:
                a0 += 0.0
                a1 += 0.0
                a2 += 0.0
                a3 += 0.0
        band[i, 0] = a0 >= threshold
        band[i + 1, 0] = a1 >= threshold
        band[i + 2, 0] = a2 >= threshold
        band[i + 3, 0] = a3 >= threshold
        for k in range(1, w):
            t_new = k + size - 1 - b
            t_old = k - 1 - b
            n0 = n1 = n2 = n3 = o0 = o1 = o2 = o3 = 0.0
            if t_new < w:
                n0 = float(mid[i, t_new])
                n1 = float(mid[i + 1, t_new])
                n2 = float(mid[i + 2, t_new])
                n3 = float(mid[i + 3, t_new])
            if t_old >= 0:
                o0 = float(mid[i, t_old])
                o1 = float(mid[i + 1, t_old])
                o2 = float(mid[i + 2, t_old])
                o3 = float(mid[i + 3, t_old])
            a0 += n0 - o0
            a1 += n1 - o1
            a2 += n2 - o2
            a3 += n3 - o3
            band[i, k] = a0 >= threshold
            band[i + 1, k] = a1 >= threshold
            band[i + 2, k] = a2 >= threshold
            band[i + 3, k] = a3 >= threshold
    for i in range(h - h % 4, h):
        a = 0.0
        for k in range(size):
            t = k - b
            a += float(mid[i, t]) if 0 <= t < w else 0.0
        band[i, 0] = a >= threshold
        for k in range(1, w):
            t_new = k + size - 1 - b
            t_old = k - 1 - b
            a += (float(mid[i, t_new]) if t_new < w else 0.0) - (float(mid[i, t_old]) if t_old >= 0 else 0.0)
            band[i, k] = a >= threshold
    return band


@njit(cache=True, nogil=True, inline="always")
def _box_line(line, buf, size, out):  # pragma: no cover - numba
    """One line of :func:`box_mean_f32`: ``line`` copied into the zero-padded ``buf`` (``size // 2``
    zeros before it), then the running sum ``+= new - old`` over ``size`` samples into ``out``."""
    b = size // 2
    for i in range(line.size):
        buf[b + i] = line[i]
    tmp = 0.0
    for k in range(size):
        tmp += buf[k]
    out[0] = tmp / size
    for k in range(1, line.size):
        tmp += buf[k + size - 1] - buf[k - 1]
        out[k] = tmp / size


@njit(cache=True, nogil=True)
def band_peak_pixels(band, img, cols):  # pragma: no cover - numba
    """Band pooling's pick: on each beam ``j`` with ``cols[j]``, the strongest ``img`` pixel of
    the first run of ``band`` rows (first maximum on ties); returns a boolean image with one pixel
    per picked beam.  Same as the numpy formulation in :func:`sonarmap.ranges.candidates.pooled_band_pixels`."""
    h, w = band.shape
    out = np.zeros((h, w), dtype=np.bool_)
    for j in range(w):
        if not cols[j]:
            continue
        i = 0
        while i < h and not band[i, j]:
            i += 1
        if i == h:
            continue
        best = i
        bv = img[i, j]
        i += 1
        while i < h and band[i, j]:
            if img[i, j] > bv:
                bv = img[i, j]
                best = i
            i += 1
        out[best, j] = True
    return out


# ------------------------------------------------------------------ ranges and sigmas of edges
@njit(cache=True, nogil=True, inline="always")
def _interp_index(fp, x):  # pragma: no cover - numba
    """``np.interp(x, np.arange(fp.size), fp)``, numpy's arithmetic (``fp`` finite)."""
    n = fp.size
    if np.isnan(x):
        return x
    if x < 0.0:
        return fp[0]
    if x >= n - 1:
        return fp[n - 1]
    j = int(x)
    if j == x:
        return fp[j]
    return (fp[j + 1] - fp[j]) * (x - j) + fp[j]


@njit(cache=True, nogil=True, inline="always")
def _edge_sigma(noise, slope, bin_m, bin_var, pulse_var, scale):  # pragma: no cover - numba
    """One value of :func:`sonarmap.ranges.echoes.edge_sigma_m` in its numpy arithmetic (NaN
    propagating through ``np.maximum`` / ``np.minimum``); ``bin_var = bin_m**2 / 12``,
    ``pulse_var = pulse_m**2 / 12``."""
    s = slope if (np.isnan(slope) or slope > 1e-12) else 1e-12
    x = np.inf if np.isnan(noise) else scale * noise / s
    if not (np.isnan(x) or x < 8.0):
        x = 8.0
    jitter = x * bin_m
    return np.sqrt(bin_var + jitter * jitter + pulse_var)


@njit(cache=True, nogil=True)
def edge_sigmas(noise, slope, bin_m, bin_var, pulse_var, scale):  # pragma: no cover - numba
    """:func:`_edge_sigma` of every element (1-D arrays of one size)."""
    out = np.empty(noise.size)
    for k in range(noise.size):
        out[k] = _edge_sigma(noise[k], slope[k], bin_m, bin_var, pulse_var, scale)
    return out


@njit(cache=True, nogil=True)
def echo_ranges(edge, peak_value, slope, range_m, fraction, sqrt2, background, sqrt_looks, bin_m, bin_var, pulse_var,
                scale):  # pragma: no cover - numba
    """Per echo the range of its edge (``np.interp`` on ``range_m``) and its sigma
    (:func:`sonarmap.ranges.echoes.range_sigma_m` at ``fraction`` x the peak)."""
    n = edge.size
    rng = np.empty(n)
    sigma = np.empty(n)
    for k in range(n):
        rng[k] = _interp_index(range_m, edge[k])
        noise = sqrt2 * (abs(fraction * peak_value[k]) + background) / sqrt_looks
        sigma[k] = _edge_sigma(noise, slope[k], bin_m, bin_var, pulse_var, scale)
    return rng, sigma


@njit(cache=True, nogil=True)
def measured_echoes(mask, img, code, lut, boost, boost_min, max_gap, fraction, peak_rel, back, forward, cols, all_cols,
                    r0, r1, range_m, sqrt2, background, sqrt_looks, bin_m, bin_var, pulse_var,
                    scale):  # pragma: no cover - numba
    """:func:`find_echoes` (``all_cols``) or :func:`find_echoes_in` of the columns ``cols``, then
    :func:`echo_ranges` of the echoes (its arguments after ``r1``) and their peaks' ranges
    (``range_m[peak]``), in one call: ``(beam, start, stop, peak, peak_value, edge, slope, evidence,
    n_pixels, edge_range, sigma, peak_range)``."""
    if all_cols:
        beam, start, stop, peak, pval, edge, slope, evid, npx = find_echoes(
            mask, img, code, lut, boost, boost_min, max_gap, fraction, peak_rel, back, forward, r0, r1)
    else:
        beam, start, stop, peak, pval, edge, slope, evid, npx = find_echoes_in(
            mask, img, code, lut, boost, boost_min, max_gap, fraction, peak_rel, back, forward, cols, r0, r1)
    edge_r, sig = echo_ranges(edge, pval, slope, range_m, fraction, sqrt2, background, sqrt_looks, bin_m, bin_var,
                              pulse_var, scale)
    peak_r = np.empty(peak.size)
    for k in range(peak.size):
        peak_r[k] = range_m[peak[k]]
    return beam, start, stop, peak, pval, edge, slope, evid, npx, edge_r, sig, peak_r


@njit(cache=True, nogil=True)
def with_edges(edge_bin, edge_range, slope, sigma, sel, beams, edge, rise, noise, range_m, bin_m, bin_var, pulse_var,
               scale, fitted, fit_scale):  # pragma: no cover - numba
    """Copies of the echoes' ``edge_bin``, ``edge_range``, ``slope``, ``sigma`` with, for each beam
    ``j`` of ``beams``, echo ``sel[j]`` given the edge ``edge[j]`` (clipped to the bins as
    ``np.clip`` does), its range, the slope ``rise[j]`` and the sigma (:func:`_edge_sigma` of
    ``noise[j]``, scaled by ``fit_scale`` where ``fitted[j]``, else by ``scale``)."""
    eb = edge_bin.copy()
    er = edge_range.copy()
    sl = slope.copy()
    sg = sigma.copy()
    top = range_m.size - 1.0
    for t in range(beams.size):
        j = beams[t]
        k = sel[j]
        x = edge[j]
        if not np.isnan(x):
            x = x if x >= 0.0 else 0.0
            x = x if x <= top else top
        eb[k] = x
        er[k] = _interp_index(range_m, x)
        sl[k] = rise[j]
        sg[k] = _edge_sigma(noise[j], rise[j], bin_m, bin_var, pulse_var, fit_scale if fitted[j] else scale)
    return eb, er, sl, sg


@njit(cache=True, nogil=True)
def track_ranges(echo, edge_bin, peak_bin, at, sigma_m, img, first_mode, start_bin, stop_bin):  # pragma: no cover - numba
    """The per-beam fields of :func:`sonarmap.ranges.ranges_from_tracks` (its numpy arithmetic):
    range ``at[e]``, bin (the edge rounded and clipped to the image, or the peak), the ``img``
    intensity at the echo's first peak ``peak_bin[e]`` (float32; in either mode), sigma, the ranges of the surfaces behind and the neighbour-support
    confidence (+-2 beams, 20 bins), for the nearest tracked echo ``e = echo[0, j]``; also the
    echo's thickness ``stop_bin[e] - start_bin[e]`` (0 where no return) and whether every beam
    without a bin (< 0) has a range that is not finite and every other a finite one."""
    n_s, m = echo.shape
    top = img.shape[0] - 1
    rng = np.full(m, np.nan)
    b = np.full(m, -1, np.int64)
    inten = np.full(m, np.nan, np.float32)
    sig = np.full(m, np.nan)
    for j in range(m):
        e = echo[0, j]
        if e < 0:
            continue
        rng[j] = at[e]
        if first_mode:
            x = np.floor(edge_bin[e] + 0.5)
            if np.isnan(x):
                b[j] = np.iinfo(np.int64).min  # what numpy's cast of NaN gives on x86
            else:
                b[j] = int(min(max(x, 0.0), top))
        else:
            b[j] = peak_bin[e]
        inten[j] = img[min(max(peak_bin[e], 0), top), j]
        sig[j] = sigma_m[e]
    other = np.full((n_s - 1, m), np.nan)
    for r in range(1, n_s):
        for j in range(m):
            if echo[r, j] >= 0:
                other[r - 1, j] = at[echo[r, j]]
    sup, cnt = support_counts(b, 2, 20)
    conf = np.zeros(m, np.float32)
    thick = np.zeros(m, np.int64)
    consistent = True
    for j in range(m):
        e = echo[0, j]
        if e >= 0:
            conf[j] = sup[j] / max(cnt[j], 1)
            thick[j] = stop_bin[e] - start_bin[e]
        if (b[j] < 0) == np.isfinite(rng[j]):
            consistent = False
    return rng, b, inten, sig, other, conf, thick, consistent


@njit(cache=True, nogil=True)
def clipped_spread(img, sel, edge_bin, peak_bin, level, bin_m, fitted, has_fitted):  # pragma: no cover - numba
    """The returns whose echo reaches ``level`` between its edge and its first peak (``peak_bin``,
    :func:`sonarmap.ranges.measure.clipped_echo_sigma`), except those whose edge is a fitted
    clipped echo's (``fitted``, when ``has_fitted``): their echo indices and the spread from the
    edge to the first clipped row (metres, > 0)."""
    n = img.shape[0]
    hit_e = np.empty(sel.size, np.int64)
    spread = np.empty(sel.size)
    k = 0
    for j in range(sel.size):
        e = sel[j]
        if e < 0 or (has_fitted and fitted[e]):
            continue
        x = np.ceil(edge_bin[e])
        lo = 0 if np.isnan(x) else int(min(max(x, 0.0), n - 1.0))
        hi = min(max(peak_bin[e] + 1, 0), n)
        for i in range(lo, hi):
            if img[i, j] >= level:
                d = (i - edge_bin[e]) * bin_m
                if d > 0:
                    hit_e[k] = e
                    spread[k] = d
                    k += 1
                break
    return hit_e[:k], spread[:k]


@njit(cache=True, nogil=True)
def clipped_gaussian_edges(img, sel, edge_bin, edge_range, sigma_m, clip_row, peak_bin, level, fitted, has_fitted,
                           max_over, range_m, bin_m):  # pragma: no cover - numba
    """:func:`sonarmap.ranges.measure.clipped_gaussian_edges`: ``(n_moved, edge_bin, edge_range,
    sigma_m)``, copies of the echoes' fields with each return of ``sel`` whose clipped first peak's
    rise is resolved moved to a Gaussian echo's half-peak crossing (its range ``np.interp`` on
    ``range_m``, the move over ``sqrt 12`` added to its sigma).  ``clip_row`` per echo (-1: not
    clipped), ``max_over`` the largest peak over full scale (linear), ``bin_m`` the bin (m);
    ``fitted`` as in :func:`clipped_spread`."""
    n = img.shape[0]
    eb = edge_bin.copy()
    er = edge_range.copy()
    sg = sigma_m.copy()
    ln2 = np.log(2.0)
    ln_max = np.log(max_over)
    n_moved = 0
    for j in range(sel.size):
        e = sel[j]
        if e < 0 or clip_row[e] < 0 or (has_fitted and fitted[e]):
            continue
        c = clip_row[e]
        x = edge_bin[e]
        # a resolved rise (half the clip level to full scale over >= 1 bin), on the first peak
        if not c - x >= 1.0 or c > peak_bin[e] + 1:
            continue
        run = 1
        while c + run < n and img[c + run, j] >= level:
            run += 1
        # the echo crosses full scale between rows c - 1 and c, and back between the run's last
        # row and the next: at c - 0.5 and c + run - 0.5, its peak midway (b >= 0.5, a >= b + 0.5:
        # the crossing below lies behind x)
        x0 = c + 0.5 * (run - 1)
        a = x0 - x
        b = x0 - (c - 0.5)
        # (a peak over max_over: a steep rise into a long clipped run is not one Gaussian echo)
        if ln2 * b * b > ln_max * (a * a - b * b):
            continue
        xh = x0 - np.sqrt(a * a - b * b)
        eb[e] = xh
        er[e] = _interp_index(range_m, xh)
        sg[e] = np.hypot(sigma_m[e], (xh - x) * bin_m / np.sqrt(12.0))
        n_moved += 1
    return n_moved, eb, er, sg


@njit(cache=True, nogil=True)
def first_intervals(sel, edge_bin, start_bin, stop_bin):  # pragma: no cover - numba
    """:func:`sonarmap.ranges.echoes._first_intervals` (non-empty echoes): per beam the edge of echo
    ``sel[j]`` (NaN: none) and the bin interval and stop of echo ``max(sel[j], 0)``, float64."""
    m = sel.size
    edge = np.empty(m)
    lo = np.empty(m)
    hi = np.empty(m)
    stop = np.empty(m)
    for j in range(m):
        e = max(sel[j], 0)
        edge[j] = edge_bin[e] if sel[j] >= 0 else np.nan
        x = np.floor(edge_bin[e])
        f = np.iinfo(np.int64).min if np.isnan(x) else int(x)  # numpy's cast of NaN on x86
        lo[j] = min(start_bin[e], f)
        hi[j] = stop_bin[e] - 1
        stop[j] = stop_bin[e]
    return edge, lo, hi, stop


@njit(cache=True, nogil=True)
def first_interval_runs(sel, edge_bin, start_bin, stop_bin, touch, jump=-1.0):  # pragma: no cover - numba
    """``(edge, stop, run)``: :func:`first_intervals`' edge and stop per beam and the
    :func:`surface_runs` of its intervals (with ``jump``), in one call."""
    edge, lo, hi, stop = first_intervals(sel, edge_bin, start_bin, stop_bin)
    return edge, stop, surface_runs(edge, lo, hi, touch, jump)


@njit(cache=True, nogil=True)
def runs_of_returns(sel, edge_bin, start_bin, stop_bin, touch):  # pragma: no cover - numba
    """:func:`first_interval_runs` and whether any beam is in a run (``run.max() >= 0``)."""
    edge, stop, run = first_interval_runs(sel, edge_bin, start_bin, stop_bin, touch, -1.0)
    for j in range(run.size):
        if run[j] >= 0:
            return edge, stop, run, True
    return edge, stop, run, False


@njit(cache=True, nogil=True)
def pooled_edges_done(sel, new, used, start_bin, stop, back):  # pragma: no cover - numba
    """The beams whose pooled edge ``new`` is kept (:func:`sonarmap.ranges.echoes.pooled_edges`):
    a return, pooled, within ``back`` bins in front of its echo's first structure bin and not
    behind its ``stop``."""
    out = np.empty(sel.size, np.int64)
    k = 0
    for j in range(sel.size):
        if sel[j] >= 0 and used[j] > 0 and new[j] >= start_bin[sel[j]] - back and new[j] <= stop[j]:
            out[k] = j
            k += 1
    return out[:k]


@njit(cache=True, nogil=True)
def kept_edges(sel, new, used, start_bin, stop, back, edge_bin, edge_range, slope, sigma, rise, noise, range_m, bin_m,
               bin_var, pulse_var, scale, fitted, fit_scale):  # pragma: no cover - numba
    """The pooled edges kept (:func:`pooled_edges_done`) given to their echoes (:func:`with_edges`)
    in one call: the number of beams kept, the echoes' new ``edge_bin``, ``edge_range``, ``slope``
    and ``sigma``, the echoes whose kept edge is that of a fitted clipped echo (``fitted``) and
    their number."""
    done = pooled_edges_done(sel, new, used, start_bin, stop, back)
    eb, er, sl, sg = with_edges(edge_bin, edge_range, slope, sigma, sel, done, new, rise, noise, range_m, bin_m,
                                bin_var, pulse_var, scale, fitted, fit_scale)
    marked = np.zeros(edge_bin.size, np.bool_)
    n_marked = 0
    for t in range(done.size):
        if fitted[done[t]]:
            marked[sel[done[t]]] = True
            n_marked += 1
    return done.size, eb, er, sl, sg, marked, n_marked


@njit(cache=True, nogil=True)
def floor_jitter(noise, rise, run, half_beams, fraction):  # pragma: no cover - numba
    """In place on ``noise``: each pooled edge's jitter ``noise / rise`` (bins) raised to at least
    ``fraction`` x the median jitter of the pooled edges of its run within ``half_beams`` on either
    side (itself included; at least 3 of them, else left alone).  A pooled profile's rise at a
    single crossing is itself noisy: on a faint echo one steep speckle step gives an edge a sigma
    a fraction of its neighbours', and in the smoothing along the surface (weights ``1 /
    sigma^2``) that edge then outweighs them all.  Edges without a finite positive jitter (not
    pooled) are left alone."""
    m = noise.size
    q = np.full(m, np.nan)
    for j in range(m):
        if run[j] >= 0 and rise[j] > 0.0 and np.isfinite(noise[j]):
            q[j] = noise[j] / rise[j]
    win = np.empty(2 * half_beams + 1)
    for j in range(m):
        if not np.isfinite(q[j]):
            continue
        c = 0
        for jj in range(max(0, j - half_beams), min(m, j + half_beams + 1)):
            if run[jj] == run[j] and np.isfinite(q[jj]):
                win[c] = q[jj]
                c += 1
        if c >= 3:
            low = fraction * _median(win, c)
            if q[j] < low:
                noise[j] = low * rise[j]


@njit(cache=True, nogil=True)
def pooled_kept_edges(sel, edge_bin, start_bin, stop_bin, touch, image, pulse_bins, half_beams, front_bins, max_bins,
                      smooth_bins, fraction, n_iter, clip, clip_level, fit_front_bins, forward, flank_bins, peak_bins,
                      back, edge_range, slope, sigma, range_m, bin_m, bin_var, pulse_var, scale, fit_scale,
                      jitter_floor, min_slope):  # pragma: no cover - numba
    """The pooled leading edges of the returns ``sel`` in one call: their runs
    (:func:`first_interval_runs` with ``touch``), :func:`pooled_edges` of them on ``image`` (float64,
    smoothed along range over ``pulse_bins`` by :func:`smooth_rows` when >= 2), with
    ``jitter_floor > 0`` their jitter floored (:func:`floor_jitter`, over twice ``half_beams``), and
    :func:`kept_edges` of its results (the arguments from ``back`` on but the last two): what
    :func:`kept_edges` returns, with no edge kept (and empty arrays) when no return belongs to a
    run.  ``min_slope``: :func:`pooled_edges`'."""
    edge, stop, run, any_run = runs_of_returns(sel, edge_bin, start_bin, stop_bin, touch)
    if not any_run:
        z = np.zeros(0)
        return 0, z, z, z, z, np.zeros(0, np.bool_), 0
    img = smooth_rows(image, pulse_bins) if pulse_bins >= 2 and image.shape[0] >= 2 else image
    new, _, rise, used, noise, fitted = pooled_edges(img, edge, stop, run, half_beams, front_bins, max_bins,
                                                     smooth_bins, fraction, n_iter, clip, clip_level, fit_front_bins,
                                                     forward, flank_bins, peak_bins, min_slope)
    if jitter_floor > 0.0:
        floor_jitter(noise, rise, run, 2 * half_beams, jitter_floor)
    return kept_edges(sel, new, used, start_bin, stop, back, edge_bin, edge_range, slope, sigma, rise, noise, range_m,
                      bin_m, bin_var, pulse_var, scale, fitted, fit_scale)


@njit(cache=True, nogil=True)
def llr_table(lp, clip):  # pragma: no cover - numba
    """:func:`sonarmap.ranges.echoes.level_llr` from ``log p(level | class)`` (>= 2 classes), in
    numpy's arithmetic: the best object class (NaN propagating) minus the background, NaN to 0,
    +-inf to +-clip, clipped."""
    n_c, n_l = lp.shape
    out = np.empty(n_l)
    for k in range(n_l):
        best = lp[1, k]
        for c in range(2, n_c):
            v = lp[c, k]
            if not (np.isnan(best) or best >= v):
                best = v
        x = best - lp[0, k]
        if np.isnan(x):
            x = 0.0
        elif x == np.inf:
            x = clip
        elif x == -np.inf:
            x = -clip
        out[k] = min(max(x, -clip), clip)
    return out


# ------------------------------------------------------------------ measurement image, clipped echoes
@njit(cache=True, nogil=True)
def excess_ratio(raw, level, full, log_db, r0, r1):  # pragma: no cover - numba
    """``max(ratio - 1, 0)`` with ``ratio = raw / b`` (``log_db <= 0``) or ``10^(log_db (raw - b) / 10)``,
    ``b = level[i] * full[i, j]``, on rows ``r0 .. r1 - 1`` (zero elsewhere); float64."""
    n, m = raw.shape
    out = np.zeros((n, m))
    excess_ratio_rows(raw, level, full, log_db, r0, r1, out)
    return out


@njit(cache=True, nogil=True)
def excess_ratio_rows(raw, level, full, log_db, r0, r1, out):  # pragma: no cover - numba
    """:func:`excess_ratio` written into rows ``r0 .. r1 - 1`` of ``out`` (zero there on entry).
    With ``log_db > 0`` the rows receive the exponent ``x`` of ``exp(x) - 1`` (clipped to ``[0,
    69]``), which the caller exponentiates (:func:`sonarmap.ranges.measure.expm1_rows`: numpy's
    vectorised exp, ~10x numba's scalar one)."""
    n, m = raw.shape
    k = log_db * np.log(10.0) / 10.0
    for i in range(max(r0, 0), min(r1, n)):
        for j in range(m):
            b = level[i] * full[i, j]
            if log_db > 0:
                x = k * (raw[i, j] - b)
                if x > 0.0:  # else exp(x) - 1 <= 0: the pixel stays 0 (much of the background)
                    out[i, j] = min(x, 69.0)
                continue
            else:
                v = raw[i, j] / max(b, 1e-12) - 1.0
            if v > 0.0:
                out[i, j] = v
    return out


@njit(cache=True, nogil=True)
def excess_ratio_grid(raw, level, grid, c0, c1, fc, g0, g1, gf, log_db, r0, r1, out):  # pragma: no cover - numba
    """:func:`excess_ratio_rows` with the beam factor interpolated from its block ``grid`` on the
    fly (``full`` = :func:`sonarmap.preprocess.normalise.expand_grid` of it, the same float32
    operations: across beams with weights ``c0, c1, fc``, then along range with ``g0, g1, gf``;
    a grid of 0 rows: factor 1), only on rows ``r0 .. r1 - 1``, which are overwritten (0 where
    the ratio is not above 1; with ``log_db > 0`` the exponent, as :func:`excess_ratio_rows`);
    ``raw`` of any real dtype (taken as float32)."""
    n, m = raw.shape
    nb = grid.shape[0]
    cols = np.ones((max(nb, 1), m), np.float32)
    one = np.float32(1.0)
    for q in range(nb):
        for j in range(m):
            cols[q, j] = grid[q, c0[j]] * (one - fc[j]) + grid[q, c1[j]] * fc[j]
    k = log_db * np.log(10.0) / 10.0
    for i in range(max(r0, 0), min(r1, n)):
        a = cols[g0[i]] if nb > 0 else cols[0]
        b = cols[g1[i]] if nb > 0 else cols[0]
        f = gf[i] if nb > 0 else np.float32(0.0)
        g = one - f
        for j in range(m):
            full = a[j] * g + b[j] * f if nb > 0 else one
            bb = level[i] * full
            v = 0.0
            if log_db > 0:
                # the exponent only (clipped to [0, 69]): the caller takes exp(x) - 1
                # (sonarmap.ranges.measure.expm1_rows)
                x = k * (np.float32(raw[i, j]) - bb)
                v = min(x, 69.0) if x > 0.0 else 0.0
            else:
                v = np.float32(raw[i, j]) / max(bb, 1e-12) - 1.0
            out[i, j] = v if v > 0.0 else 0.0
    return out


@njit(cache=True, nogil=True)
def top_counts(img, top, below):  # pragma: no cover - numba
    """``(n_top, n_below)``: the samples of ``img`` equal to ``top`` (its maximum) and those in
    ``[top - below, top)`` (one pass, compared in float64 as the clip kernels compare)."""
    n_top = 0
    n_near = 0
    lo = top - below
    flat = img.ravel()
    # (branch-free counts: the loop vectorises)
    for k in range(flat.size):
        v = np.float64(flat[k])
        n_top += v >= top
        n_near += v >= lo
    return n_top, n_near - n_top


@njit(cache=True, nogil=True, inline="always")
def _gather2(a, b, take):  # pragma: no cover - numba
    """``np.concatenate([a, b])[take]``."""
    n_a = a.size
    out = np.empty(take.size, a.dtype)
    for t in range(take.size):
        k = take[t]
        out[t] = a[k] if k < n_a else b[k - n_a]
    return out


@njit(cache=True, nogil=True)
def spliced_fields(columns, n_beams, beam, start, stop, peak, npx, clip_row, pval, edge, edge_r, peak_r, slope, evid,
                   sigma, clipped, n_beam, n_start, n_stop, n_peak, n_npx, n_clip_row, n_pval, n_edge, n_edge_r,
                   n_peak_r, n_slope, n_evid, n_sigma, n_clipped):  # pragma: no cover - numba
    """:func:`sonarmap.ranges.echoes.spliced_echoes` of the per-echo fields (the old echoes', then
    the new ones', ``n_``): the old echoes off the beams ``columns`` and the new ones, in the
    stable order by beam (numpy's stable argsort of the two, concatenated), each field gathered
    once: ``(beam, start, stop, peak, n_pixels, clip_row, peak_value, edge, edge_range,
    peak_range, slope, evidence, sigma, clipped)``."""
    keep = np.ones(n_beams, np.bool_)
    for c in columns:
        keep[c] = False
    idx = np.empty(beam.size + n_beam.size, np.int64)
    key = np.empty(idx.size, np.int64)
    c = 0
    for k in range(beam.size):
        if keep[beam[k]]:
            idx[c] = k
            key[c] = beam[k]
            c += 1
    for k in range(n_beam.size):
        idx[c] = beam.size + k
        key[c] = n_beam[k]
        c += 1
    take = idx[:c][np.argsort(key[:c], kind="mergesort")]
    return (_gather2(beam, n_beam, take), _gather2(start, n_start, take), _gather2(stop, n_stop, take),
            _gather2(peak, n_peak, take), _gather2(npx, n_npx, take), _gather2(clip_row, n_clip_row, take),
            _gather2(pval, n_pval, take), _gather2(edge, n_edge, take), _gather2(edge_r, n_edge_r, take),
            _gather2(peak_r, n_peak_r, take), _gather2(slope, n_slope, take), _gather2(evid, n_evid, take),
            _gather2(sigma, n_sigma, take), _gather2(clipped, n_clipped, take))


@njit(cache=True, nogil=True)
def first_clipped_rows(img, cols, lo, hi, level):  # pragma: no cover - numba
    """Per ``k``, the first row in ``lo[k] .. hi[k] - 1`` (both clipped to ``0 .. n_rows``) of
    column ``cols[k]`` of ``img`` that reaches ``level`` (-1 if none).

    Where the intervals cover more than an eighth of the rows they span, the samples reaching
    ``level`` are listed per column from one pass along the rows of that span first (a walk down
    the columns of a tall image misses the cache at every row); else each interval is walked."""
    out = np.full(cols.size, -1, dtype=np.int64)
    n, m = img.shape
    lo = np.minimum(np.maximum(lo, 0), n)
    hi = np.minimum(np.maximum(hi, 0), n)
    r0 = n
    r1 = 0
    covered = 0
    for k in range(cols.size):
        if hi[k] > lo[k]:
            r0 = min(r0, lo[k])
            r1 = max(r1, hi[k])
            covered += hi[k] - lo[k]
    if covered * 8 <= (r1 - r0) * m:
        for k in range(cols.size):
            j = cols[k]
            for i in range(lo[k], hi[k]):
                if img[i, j] >= level:
                    out[k] = i
                    break
        return out
    # the rows reaching level of each column, ascending, less r0: rows[first[j] : first[j + 1]]
    # (_clipped_rows: a vectorised test per row, the lists only from the rows with such a sample)
    first, rows = _clipped_rows(img[r0:r1], level)
    if rows.size == 0:
        return out
    for k in range(cols.size):
        j = cols[k]
        # the first listed row at or after lo[k] (binary search), if before hi[k]
        a = first[j]
        b = first[j + 1]
        while a < b:
            c = (a + b) // 2
            if rows[c] < lo[k] - r0:
                a = c + 1
            else:
                b = c
        if a < first[j + 1] and rows[a] < hi[k] - r0:
            out[k] = rows[a] + r0
    return out


@njit(cache=True, nogil=True, inline="always")
def _edge_hi(pos, clip_rise, c):  # pragma: no cover - numba
    """The far end of echo ``c``'s edge interval: its edge, or for a clipped echo its first
    full-scale sample (``pos + clip_rise``: the unclipped echo's half-peak lies in between)."""
    return pos[c] + clip_rise[c] if clip_rise[c] > 0.0 else pos[c]


@njit(cache=True, nogil=True, inline="always")
def _gap(a_lo, a_hi, b_lo, b_hi):  # pragma: no cover - numba
    """Distance between the intervals ``[a_lo, a_hi]`` and ``[b_lo, b_hi]`` (0 when they overlap)."""
    return max(0.0, b_lo - a_hi, a_lo - b_hi)


@njit(cache=True, nogil=True, inline="always")
def _is_point_run(chosen, pos, peak_val, point, clip_rise, width_beams, s, k, split_l, split_r, flat_lo, flat_hi,
                  jump_bins, dip, over_range, margin, lo_beam, hi_beam):  # pragma: no cover - numba
    """Whether the chosen echoes on beams ``s .. k - 1`` (a flat run of one piece, or the whole
    piece; ``[flat_lo, flat_hi]`` its mean edge interval) can be one point target's streak: at least
    half point echoes, a real range jump (or the piece's end, or a dip) at both ends and no wider
    than the main lobe lets a point be (see :func:`point_pieces`)."""
    n = k - s
    if n < 2:
        return False
    n_echo = 0
    n_pt = 0
    peak = 0.0
    weakest = np.inf
    any_clip = False
    bw = 0.0
    for q in range(s, k):
        bw += width_beams[q]
        c = chosen[q]
        if c < 0:
            continue
        n_echo += 1
        if point[c]:
            n_pt += 1
        peak = max(peak, peak_val[c])
        weakest = min(weakest, peak_val[c])
        if clip_rise[c] >= 0.0:
            any_clip = True
    if 2 * n_pt < n_echo:
        return False
    # ends: the piece ends, a beam without an echo, a dip, a range jump, or the streak's own tail
    # (an echo weaker than dip x the run's weakest, whose edge the weak level moves)
    if not split_l and s > lo_beam and chosen[s - 1] >= 0 \
            and _gap(pos[chosen[s - 1]], _edge_hi(pos, clip_rise, chosen[s - 1]), flat_lo, flat_hi) < jump_bins \
            and peak_val[chosen[s - 1]] >= dip * weakest:
        return False
    if not split_r and k <= hi_beam and chosen[k] >= 0 \
            and _gap(pos[chosen[k]], _edge_hi(pos, clip_rise, chosen[k]), flat_lo, flat_hi) < jump_bins \
            and peak_val[chosen[k]] >= dip * weakest:
        return False
    # width: a Gaussian main lobe W beams wide holds a point over W sqrt(log2(peak / level)) above
    # a level; the run's weakest echo bounds the level its ends reach
    ratio = peak * (over_range if any_clip else 1.0) / max(weakest, 1e-12)
    cap = (bw / n) * np.sqrt(max(np.log2(ratio), 0.0)) if ratio > 1.0 else 0.0
    return n - 1 <= margin * cap


@njit(cache=True, nogil=True)
def _piece_end(chosen, pos, lo_bin, hi_bin, j, max_gap, jump_bins, touch_bins):  # pragma: no cover - numba
    """The last beam of the piece starting at beam ``j`` (the tracker's neighbour rule)."""
    m = chosen.size
    k = j
    while True:
        nxt = -1
        for g in range(1, max_gap + 2):
            q = k + g
            if q >= m:
                break
            if chosen[q] >= 0:
                if _neighbours(chosen[q], chosen[k], g, pos, lo_bin, hi_bin, jump_bins, touch_bins):
                    nxt = q
                break
        if nxt < 0:
            return k
        k = nxt


@njit(cache=True, nogil=True)
def point_pieces(chosen, pos, peak_val, point, clip_rise, evidence, width_beams, lo_bin, hi_bin, max_gap,
                 jump_bins, touch_bins, pulse_bins, flat_bins, point_jump_bins, dip, over_range, margin,
                 fraction):  # pragma: no cover - numba
    """Beams of the tracked pieces that are point targets, not surfaces (see
    :func:`sonarmap.ranges.tracking.point_streaks`).

    ``chosen``: one pass's echo per beam (-1 none).  A piece is a chain of chosen echoes on beams at
    most ``max_gap + 1`` apart, each a neighbour of the one before (the tracker's rule).  An echo's
    edge is the interval ``[pos, pos + clip_rise]`` when it is clipped (``clip_rise >= 0``), else
    ``pos``; distances are between intervals.  A piece whose edges lie within ``pulse_bins`` of
    each other is one run (all its beams are returned when it is a point streak); else its flat
    runs (consecutive beams, each edge within ``flat_bins`` of the mean edge of the run before it)
    are split at dips of the peak value (below ``dip`` x the larger peak on each side: a main lobe
    is unimodal); a run is a point streak when :func:`_is_point_run` says so.  Returns True on
    every beam of a piece whose point streaks hold at least ``fraction`` of its evidence.
    """
    m = chosen.size
    drop = np.zeros(m, np.bool_)
    j = 0
    while j < m:
        if chosen[j] < 0:
            j += 1
            continue
        # one piece: from beam j to the last beam chained to it
        last = _piece_end(chosen, pos, lo_bin, hi_bin, np.int64(j), max_gap, jump_bins, touch_bins)
        # the whole piece at one range (its edge intervals within a pulse) and no wider than a point
        lo_e = np.inf
        hi_e = -np.inf
        for q in range(j, last + 1):
            if chosen[q] >= 0:
                lo_e = min(lo_e, _edge_hi(pos, clip_rise, chosen[q]))
                hi_e = max(hi_e, pos[chosen[q]])
        if hi_e - lo_e <= pulse_bins and _is_point_run(
                chosen, pos, peak_val, point, clip_rise, width_beams, j, last + 1, True, True, 0.0, 0.0,
                point_jump_bins, dip, over_range, margin, j, last):
            for q in range(j, last + 1):
                if chosen[q] >= 0:
                    drop[q] = True
            j = last + 1
            continue
        ev_all = 0.0
        ev_point = 0.0
        s = j
        while s <= last:
            if chosen[s] < 0:
                s += 1
                continue
            # a flat run from s: each edge interval within flat_bins of the run's mean interval
            total = pos[chosen[s]]
            total_hi = _edge_hi(pos, clip_rise, chosen[s])
            e = s + 1
            while e <= last and chosen[e] >= 0 and _gap(pos[chosen[e]], _edge_hi(pos, clip_rise, chosen[e]),
                                                        total / (e - s), total_hi / (e - s)) <= flat_bins:
                total += pos[chosen[e]]
                total_hi += _edge_hi(pos, clip_rise, chosen[e])
                e += 1
            mean = total / (e - s)
            mean_hi = total_hi / (e - s)
            # split it at dips of the peak value; each part (the last one ends the run) is tested
            a = s
            for u in range(s + 1, e + 1):
                if u < e:
                    left = 0.0
                    for q in range(a, u):
                        left = max(left, peak_val[chosen[q]])
                    right = 0.0
                    for q in range(u + 1, e):
                        right = max(right, peak_val[chosen[q]])
                    if not (u + 1 < e and peak_val[chosen[u]] < dip * min(left, right)):
                        continue
                ok = _is_point_run(chosen, pos, peak_val, point, clip_rise, width_beams, a, u, a != s, u < e, mean,
                                   mean_hi, point_jump_bins, dip, over_range, margin, j, last)
                for q in range(a, u):
                    ev = max(evidence[chosen[q]], 0.0)
                    ev_all += ev
                    ev_point += ev if ok else 0.0
                a = u
            s = e
        if ev_all > 0.0 and ev_point >= fraction * ev_all:
            for q in range(j, last + 1):
                if chosen[q] >= 0:
                    drop[q] = True
        j = last + 1
    return drop
