"""Numba kernels of the range stage (private; see :mod:`sonarmap.ranges.echoes` and
:mod:`sonarmap.ranges.tracking`).

Images are ``(n_bins, n_beams)``; an echo is identified by its index in the flat per-echo arrays,
sorted by beam and then by range.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def find_echoes(mask, img, code, lut, boost, boost_min, max_gap, fraction, peak_rel, back, forward):  # pragma: no cover - numba
    """Echoes along every beam (see :func:`sonarmap.ranges.echoes.find_echoes`).

    Returns per echo: beam, start, stop (exclusive, structure pixels), peak bin, peak value,
    edge position (fractional bin index of the ``fraction`` crossing), edge slope (value per
    bin at the crossing), evidence (sum over the echo's structure pixels of ``lut[code[i, j]]``,
    at least ``boost_min`` where ``boost`` (shape (1, 1): nowhere) is set) and its number of
    structure pixels.
    """
    has_boost = boost.shape[0] == mask.shape[0]
    n, m = mask.shape
    # echoes are separated by more than max_gap bins: an upper bound of their number
    n_echoes = m * (n // (max_gap + 2) + 1)
    beam = np.empty(n_echoes, np.int64)
    start = np.empty(n_echoes, np.int64)
    stop = np.empty(n_echoes, np.int64)
    peak = np.empty(n_echoes, np.int64)
    peak_val = np.empty(n_echoes, np.float64)
    edge = np.empty(n_echoes, np.float64)
    slope = np.empty(n_echoes, np.float64)
    evidence = np.empty(n_echoes, np.float64)
    n_pix = np.empty(n_echoes, np.int64)
    k = 0
    for j in range(m):
        i = 0
        while i < n:
            if not mask[i, j]:
                i += 1
                continue
            s = i
            last = i
            ev = 0.0
            npx = 0
            while i < n and (mask[i, j] or i - last <= max_gap):
                if mask[i, j]:
                    last = i
                    v = lut[code[i, j]]
                    if has_boost and boost[i, j] and v < boost_min:
                        v = boost_min
                    ev += v
                    npx += 1
                i += 1
            e = last + 1
            i = e
            # first peak: the first local maximum reaching peak_rel of the echo's maximum
            vmax = img[s, j]
            for q in range(s + 1, e):
                if img[q, j] > vmax:
                    vmax = img[q, j]
            p = s
            while p < e - 1 and not (img[p, j] >= peak_rel * vmax and img[p, j] >= img[p + 1, j]):
                p += 1
            # the peak's height, refined by a parabola through its neighbours (a sampled peak is
            # lower than the echo's: the half-peak level would move with the sampling phase)
            pv = img[p, j]
            if 0 < p < n - 1 and img[p - 1, j] < pv and img[p + 1, j] < pv:
                den = img[p - 1, j] - 2.0 * pv + img[p + 1, j]
                if den < 0.0:
                    pv = pv - 0.125 * (img[p - 1, j] - img[p + 1, j]) ** 2 / den
            level = fraction * pv
            # the leading edge, at most `back` bins in front of the echo
            lo = s - back
            if lo < 0:
                lo = 0
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
                pos = (q - 1) + (level - img[q - 1, j]) / d
                sl = d
            else:
                pos = float(q)
                sl = img[p, j] if p == q else (img[p, j] - img[q, j]) / (p - q)
            beam[k] = j
            start[k] = s
            stop[k] = e
            peak[k] = p
            peak_val[k] = pv
            edge[k] = pos
            slope[k] = sl
            evidence[k] = ev
            n_pix[k] = npx
            k += 1
    return (beam[:k].copy(), start[:k].copy(), stop[:k].copy(), peak[:k].copy(), peak_val[:k].copy(),
            edge[:k].copy(), slope[:k].copy(), evidence[:k].copy(), n_pix[:k].copy())


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
    for j in range(m):
        base = done[j]  # best finished before beam j (start a new piece here)
        for a in range(first[j], first[j] + count[j]):
            if not usable[a]:
                continue
            c = base + segment_cost
            pa = -1
            for g in range(1, max_gap + 2):
                jb = j - g
                if jb < 0:
                    break
                for b in range(first[jb], first[jb] + count[jb]):
                    if not usable[b] or best[b] == np.inf:
                        continue
                    d = abs(pos[a] - pos[b]) / g
                    if d > jump_bins:
                        continue
                    # contiguity: the two echoes' bin intervals lie within touch_bins per beam
                    sep = max(lo_bin[a] - hi_bin[b], lo_bin[b] - hi_bin[a])
                    if sep > touch_bins * g:
                        continue
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
def excess_ratio(raw, level, full, log_db, r0, r1):  # pragma: no cover - numba
    """``max(ratio - 1, 0)`` with ``ratio = raw / b`` (``log_db <= 0``) or ``10^(log_db (raw - b) / 10)``,
    ``b = level[i] * full[i, j]``, on rows ``r0 .. r1 - 1`` (zero elsewhere); float64."""
    n, m = raw.shape
    out = np.zeros((n, m))
    k = log_db * np.log(10.0) / 10.0
    for i in range(max(r0, 0), min(r1, n)):
        for j in range(m):
            b = level[i] * full[i, j]
            if log_db > 0:
                x = k * (raw[i, j] - b)
                if x > 69.0:
                    x = 69.0
                v = np.exp(x) - 1.0
            else:
                v = raw[i, j] / max(b, 1e-12) - 1.0
            if v > 0.0:
                out[i, j] = v
    return out
