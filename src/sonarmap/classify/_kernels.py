"""Numba kernels for the MRF solvers (private; see :mod:`sonarmap.classify.mrf`).

Lattice conventions shared by every kernel
-----------------------------------------
* ``unary``: float64 ``(n_labels, n_bins, n_beams)``, the cost of each label at each pixel.
* ``weights``: float64 ``(n_dirs, n_bins, n_beams)`` with ``n_dirs`` 2 (4-neighbourhood) or 4
  (8-neighbourhood).  ``weights[d, i, j]`` is the Potts weight of the edge from ``(i, j)`` to
  ``(i + DI[d], j + DJ[d])``; entries whose partner lies outside the lattice are zero.
* ``labels``: int32 ``(n_bins, n_beams)``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# direction offsets: down (range), right (beam), down-right, down-left
DI = np.array([1, 0, 1, 1], dtype=np.int64)
DJ = np.array([0, 1, 1, -1], dtype=np.int64)


@njit(cache=True, nogil=True, inline="always")
def _label_costs(unary, weights, labels, i, j, out):  # pragma: no cover - numba
    n_labels, h, w = unary.shape
    n_dirs = weights.shape[0]
    for lab in range(n_labels):
        out[lab] = unary[lab, i, j]
    for d in range(n_dirs):
        di = DI[d]
        dj = DJ[d]
        # forward neighbour
        ii = i + di
        jj = j + dj
        if 0 <= ii < h and 0 <= jj < w:
            wt = weights[d, i, j]
            if wt != 0.0:
                lq = labels[ii, jj]
                for lab in range(n_labels):
                    if lab != lq:
                        out[lab] += wt
        # backward neighbour
        ii = i - di
        jj = j - dj
        if 0 <= ii < h and 0 <= jj < w:
            wt = weights[d, ii, jj]
            if wt != 0.0:
                lq = labels[ii, jj]
                for lab in range(n_labels):
                    if lab != lq:
                        out[lab] += wt


@njit(cache=True, nogil=True)
def icm(unary, weights, labels, max_sweeps):  # pragma: no cover - numba
    """Iterated conditional modes in raster order, in place; returns the number of sweeps."""
    n_labels, h, w = unary.shape
    costs = np.empty(n_labels)
    sweeps = 0
    for _ in range(max_sweeps):
        sweeps += 1
        changed = 0
        for i in range(h):
            for j in range(w):
                _label_costs(unary, weights, labels, i, j, costs)
                best = labels[i, j]
                bc = costs[best]
                for lab in range(n_labels):
                    if costs[lab] < bc:
                        bc = costs[lab]
                        best = lab
                if best != labels[i, j]:
                    labels[i, j] = best
                    changed += 1
        if changed == 0:
            break
    return sweeps


@njit(cache=True, nogil=True)
def anneal(unary, weights, labels, temperatures, seed):  # pragma: no cover - numba
    """Gibbs-sampler simulated annealing (Geman & Geman 1984), in place.

    One raster sweep per temperature; each pixel's label is drawn from
    ``p(l) ~ exp(-cost(l) / T)`` given its neighbours.
    """
    np.random.seed(seed)
    n_labels, h, w = unary.shape
    costs = np.empty(n_labels)
    probs = np.empty(n_labels)
    for t in range(temperatures.size):
        temp = temperatures[t]
        for i in range(h):
            for j in range(w):
                _label_costs(unary, weights, labels, i, j, costs)
                cmin = costs.min()
                tot = 0.0
                for lab in range(n_labels):
                    probs[lab] = np.exp(-(costs[lab] - cmin) / temp)
                    tot += probs[lab]
                u = np.random.random() * tot
                acc = 0.0
                choice = n_labels - 1
                for lab in range(n_labels):
                    acc += probs[lab]
                    if u < acc:
                        choice = lab
                        break
                labels[i, j] = choice


@njit(cache=True, nogil=True, inline="always")
def _pull(f, wt, acc):  # pragma: no cover - numba
    """(free weight, margin change) contribution of one neighbour state ``f``."""
    if f < 0:
        return wt, acc
    if f == 1:
        return 0.0, acc + wt
    return 0.0, acc - wt


@njit(cache=True, nogil=True, inline="always")
def _settle(fixed, i, j, mm, wf):  # pragma: no cover - numba
    """Fix (i, j) to the label its effective margin ``mm`` favours if ``|mm|`` beats the free
    edge weight ``wf``; returns 1 if fixed."""
    if mm > wf:
        fixed[i, j] = 1
        return 1
    if mm < -wf:
        fixed[i, j] = 0
        return 1
    return 0


@njit(cache=True, nogil=True, inline="always")
def _try_fix(levels, margin_lut, weights, fixed, i, j, h, w):  # pragma: no cover - numba
    """Fix (i, j) if its effective margin beats the weight of its free edges; returns 1 if fixed."""
    mm = margin_lut[levels[i, j]]
    wf = 0.0
    if weights.shape[0] == 2 and 0 < i < h - 1 and 0 < j < w - 1:
        # interior pixel of a 4-neighbourhood: unrolled
        a, mm = _pull(fixed[i + 1, j], weights[0, i, j], mm)
        wf += a
        a, mm = _pull(fixed[i - 1, j], weights[0, i - 1, j], mm)
        wf += a
        a, mm = _pull(fixed[i, j + 1], weights[1, i, j], mm)
        wf += a
        a, mm = _pull(fixed[i, j - 1], weights[1, i, j - 1], mm)
        wf += a
        return _settle(fixed, i, j, mm, wf)
    for d in range(weights.shape[0]):
        di = DI[d]
        dj = DJ[d]
        ii = i + di
        jj = j + dj
        if 0 <= ii < h and 0 <= jj < w:
            a, mm = _pull(fixed[ii, jj], weights[d, i, j], mm)
            wf += a
        ii = i - di
        jj = j - dj
        if 0 <= ii < h and 0 <= jj < w:
            a, mm = _pull(fixed[ii, jj], weights[d, ii, jj], mm)
            wf += a
    return _settle(fixed, i, j, mm, wf)


@njit(cache=True, nogil=True, inline="always")
def _try_fix_u(levels, margin_lut, weights, fixed, i, j, h, w, wr, wb):  # pragma: no cover - numba
    """:func:`_try_fix` for uniform 4-neighbourhood weights (``wr`` along range, ``wb`` across
    beams) - interior pixels read no weight array."""
    if 0 < i < h - 1 and 0 < j < w - 1:
        mm = margin_lut[levels[i, j]]
        wf, mm = _pull(fixed[i + 1, j], wr, mm)
        a, mm = _pull(fixed[i - 1, j], wr, mm)
        wf += a
        a, mm = _pull(fixed[i, j + 1], wb, mm)
        wf += a
        a, mm = _pull(fixed[i, j - 1], wb, mm)
        wf += a
        return _settle(fixed, i, j, mm, wf)
    return _try_fix(levels, margin_lut, weights, fixed, i, j, h, w)


@njit(cache=True, nogil=True)
def reduce_binary(levels, margin_lut, weights, wtot, fixed, node, m, wfree, stack, uniform, max_sweeps=256):  # pragma: no cover
    """Exact persistency reduction of a binary Potts problem, then graph arrays for the rest.

    The margin of pixel ``(i, j)`` is ``margin_lut[levels[i, j]]`` (``unary[0] - unary[1]``,
    positive favours label 1); a general unary is passed as ``levels = arange(h*w)`` and
    ``margin_lut = margin.ravel()``.  ``wtot`` is the total incident edge weight per pixel;
    ``fixed``, ``node``, ``m``, ``wfree`` and ``stack`` are caller-owned work arrays (reused
    across pings of equal shape, so no large allocation happens per call; ``m`` and ``wfree``
    are unused and kept for the signature).

    A pixel whose effective margin - its own plus ``+w`` for every edge to a neighbour already
    fixed to 1 and ``-w`` for one fixed to 0 - exceeds the total weight of its edges to still-free
    neighbours takes the label the margin favours in *every* minimiser (changing it alone would
    lower the energy strictly, whatever the free neighbours do).  The test is monotone (fixing a
    neighbour lowers the free weight by ``w`` and moves the margin by at most ``w``, so a fixable
    pixel stays fixable with the same label), hence the fixed point does not depend on the
    propagation order.  Pass 1 is one forward raster sweep in which the unconditional test
    ``|margin| > wtot`` (no neighbour reads) settles most pixels and only the others read their
    already-visited neighbours; its survivors (a few per cent) are then swept, in alternating
    backward and forward order, with the full test until nothing changes or ``max_sweeps``
    sweeps have run (what is left free goes to the cut, which is exact either way).  No lattice-sized
    initialisation pass is needed.

    Returns
    -------
    n_free : int
    m_eff : float64 (n_free,)
        Effective margin of each free node (``node[i, j]`` is its index, valid only where
        ``fixed[i, j] < 0``).
    ei, ej : int64 (n_edges,), ew : float64 (n_edges,)
        Free-free edges and their weights.  ``fixed`` holds 0/1, or -1 for free pixels.
    """
    h, w = levels.shape
    n_dirs = weights.shape[0]
    uni = uniform.size == 2 and n_dirs == 2
    wr = uniform[0] if uni else 0.0
    wb = uniform[1] if uni else 0.0
    # pass 1, forward raster order: the unconditional test |margin| > wtot (no neighbour reads)
    # decides most pixels; the rest get the full test with their already-visited (backward)
    # neighbours' states - the forward neighbours are not visited yet, hence free
    n_left = 0
    for i in range(h):
        for j in range(w):
            mm = margin_lut[levels[i, j]]
            t = wtot[i, j]
            if mm > t:
                fixed[i, j] = 1
                continue
            if mm < -t:
                fixed[i, j] = 0
                continue
            if uni and i > 0 and j > 0 and i < h - 1 and j < w - 1:
                wf = wr + wb
                a, mm = _pull(fixed[i - 1, j], wr, mm)
                wf += a
                a, mm = _pull(fixed[i, j - 1], wb, mm)
                wf += a
            else:
                wf = 0.0
                for d in range(n_dirs):
                    ii = i + DI[d]
                    jj = j + DJ[d]
                    if 0 <= ii < h and 0 <= jj < w:
                        wf += weights[d, i, j]
                    ii = i - DI[d]
                    jj = j - DJ[d]
                    if 0 <= ii < h and 0 <= jj < w:
                        a, mm = _pull(fixed[ii, jj], weights[d, ii, jj], mm)
                        wf += a
            if not _settle(fixed, i, j, mm, wf):
                fixed[i, j] = -1
                stack[n_left] = i * w + j          # ascending raster order
                n_left += 1
    # propagation: alternating backward / forward sweeps over the undecided pixels with the full
    # test, compacting the list in place (it stays in ascending raster order in stack[lo:hi])
    lo = 0
    hi = n_left
    changed = 1
    sweep = 0
    while changed and sweep < max_sweeps:
        changed = 0
        if sweep % 2 == 1:
            k_out = lo
            for k in range(lo, hi):                # forward
                p = stack[k]
                i = p // w
                j = p - i * w
                if _try_fix_u(levels, margin_lut, weights, fixed, i, j, h, w, wr, wb) if uni else \
                        _try_fix(levels, margin_lut, weights, fixed, i, j, h, w):
                    changed += 1
                else:
                    stack[k_out] = p
                    k_out += 1
            hi = k_out
        else:
            k_out = hi - 1
            for k in range(hi - 1, lo - 1, -1):   # backward
                p = stack[k]
                i = p // w
                j = p - i * w
                if _try_fix_u(levels, margin_lut, weights, fixed, i, j, h, w, wr, wb) if uni else \
                        _try_fix(levels, margin_lut, weights, fixed, i, j, h, w):
                    changed += 1
                else:
                    stack[k_out] = p
                    k_out -= 1
            lo = k_out + 1
        sweep += 1
    # number the survivors (ascending raster order) and list their edges
    n_free = hi - lo
    for a in range(n_free):
        p = stack[lo + a]
        stack[a] = p
        i = p // w
        node[i, p - i * w] = a
    m_eff = np.empty(n_free)
    ei = np.empty(n_free * n_dirs, dtype=np.int64)
    ej = np.empty(n_free * n_dirs, dtype=np.int64)
    ew = np.empty(n_free * n_dirs)
    n_edges = 0
    for a in range(n_free):
        p = stack[a]
        i = p // w
        j = p - i * w
        mm = margin_lut[levels[i, j]]
        for d in range(n_dirs):
            di = DI[d]
            dj = DJ[d]
            ii = i + di
            jj = j + dj
            if 0 <= ii < h and 0 <= jj < w:
                wt = weights[d, i, j]
                f = fixed[ii, jj]
                if f < 0:
                    if wt != 0.0:
                        ei[n_edges] = a
                        ej[n_edges] = node[ii, jj]
                        ew[n_edges] = wt
                        n_edges += 1
                elif f == 1:
                    mm += wt
                else:
                    mm -= wt
            ii = i - di
            jj = j - dj
            if 0 <= ii < h and 0 <= jj < w:
                f = fixed[ii, jj]
                if f == 1:
                    mm += weights[d, ii, jj]
                elif f == 0:
                    mm -= weights[d, ii, jj]
        m_eff[a] = mm
    return n_free, m_eff, ei[:n_edges], ej[:n_edges], ew[:n_edges]


@njit(cache=True, nogil=True)
def write_free_labels(fixed, node, x, labels):  # pragma: no cover - numba
    """``labels = fixed`` with free pixels set from the cut ``x[node]``."""
    h, w = fixed.shape
    for i in range(h):
        for j in range(w):
            f = fixed[i, j]
            labels[i, j] = x[node[i, j]] if f < 0 else f


@njit(cache=True, nogil=True)
def energy_lut(levels, cost_lut, weights, labels):  # pragma: no cover - numba
    """Energy with unary ``cost_lut[label, levels[i, j]]`` plus Potts pairwise terms."""
    h, w = levels.shape
    e = 0.0
    for i in range(h):
        for j in range(w):
            e += cost_lut[labels[i, j], levels[i, j]]
    for d in range(weights.shape[0]):
        di = DI[d]
        dj = DJ[d]
        j0 = max(0, -dj)
        j1 = w - max(0, dj)
        for i in range(h - di):
            for j in range(j0, j1):
                if labels[i, j] != labels[i + di, j + dj]:
                    e += weights[d, i, j]
    return e


@njit(cache=True, nogil=True)
def gather_costs(levels, cost):  # pragma: no cover - numba
    """``out[k, i, j] = cost[k, levels[i, j]]`` as float64."""
    n = cost.shape[0]
    h, w = levels.shape
    out = np.empty((n, h, w))
    for k in range(n):
        for i in range(h):
            for j in range(w):
                out[k, i, j] = cost[k, levels[i, j]]
    return out


@njit(cache=True, nogil=True)
def expansion_arrays(unary, weights, labels, alpha):  # pragma: no cover - numba
    """Graph arrays of one alpha-expansion move (Boykov, Veksler & Zabih 2001) for Potts terms.

    Binary variable ``x_p = 1`` means "switch to ``alpha``".  Per edge with current labels
    ``(a, b)`` the move energies are ``E00 = w[a != b]``, ``E01 = w[a != alpha]``,
    ``E10 = w[alpha != b]``, ``E11 = 0``; they are regular for the Potts metric and decomposed as
    ``E00 + (E10 - E00) x_p + (E11 - E10) x_q + (E01 + E10 - E00 - E11)(1 - x_p) x_q``.

    Returns per-pixel costs ``c0`` (keep) and ``c1`` (switch), flattened, and edges
    ``(ei, ej, cap)`` for the ``(1 - x_p) x_q`` terms.
    """
    n_labels, h, w = unary.shape
    n_dirs = weights.shape[0]
    c0 = np.empty(h * w)
    c1 = np.empty(h * w)
    for i in range(h):
        for j in range(w):
            c0[i * w + j] = unary[labels[i, j], i, j]
            c1[i * w + j] = unary[alpha, i, j]
    n_max = h * w * n_dirs
    ei = np.empty(n_max, dtype=np.int64)
    ej = np.empty(n_max, dtype=np.int64)
    cap = np.empty(n_max)
    k = 0
    for d in range(n_dirs):
        for i in range(h):
            for j in range(w):
                ii = i + DI[d]
                jj = j + DJ[d]
                if not (0 <= ii < h and 0 <= jj < w):
                    continue
                wt = weights[d, i, j]
                if wt == 0.0:
                    continue
                a = labels[i, j]
                b = labels[ii, jj]
                e00 = wt if a != b else 0.0
                e01 = wt if a != alpha else 0.0
                e10 = wt if alpha != b else 0.0
                p = i * w + j
                q = ii * w + jj
                # constant E00 on both of p's costs, + (E10 - E00) x_p, + (E11 - E10) x_q
                c0[p] += e00
                c1[p] += e10
                c1[q] -= e10
                c = e01 + e10 - e00
                if c > 0.0:
                    ei[k] = p
                    ej[k] = q
                    cap[k] = c
                    k += 1
    return c0, c1, ei[:k], ej[:k], cap[:k]


# ----------------------------------------------------------------------------- range extraction


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
    jmin = np.full(n, w, dtype=np.int32)
    jmax = np.full(n, -1, dtype=np.int32)
    imin = np.full(n, h, dtype=np.int32)
    imax = np.full(n, -1, dtype=np.int32)
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
def linked_components(mask, min_beams, min_bins, gap, rounds, idx, min_pixels=0):  # pragma: no cover - numba
    """Rule 0 of :func:`sonarmap.ranges.extract_ranges` in one kernel: the 8-connected components
    of ``mask`` spanning >= ``min_beams`` beams or >= ``min_bins`` bins (``min_bins <= 0``: beams
    only) or holding >= ``min_pixels`` pixels (``min_pixels <= 0``: off), then up to ``rounds``
    rounds adding every other component with a pixel within ``gap`` beams and 1 bin of a pixel
    kept at the start of the round (stopping at the first round that adds nothing).

    Same result as :func:`wide_components` followed by ``_link_components`` (whose components of
    ``mask & ~kept`` are exactly the components of ``mask`` not kept yet), but the lattice is
    labelled once.  ``idx`` is a caller-owned int32 work array of ``mask``'s shape that must be
    all -1 on entry; it is restored to -1 before returning.
    """
    h, w = mask.shape
    n = 0
    for i in range(h):
        for j in range(w):
            if mask[i, j]:
                n += 1
    pi = np.empty(n, dtype=np.int32)
    pj = np.empty(n, dtype=np.int32)
    n = 0
    for i in range(h):
        for j in range(w):
            if mask[i, j]:
                idx[i, j] = n
                pi[n] = i
                pj[n] = j
                n += 1
    parent = np.arange(n, dtype=np.int32)
    for a in range(n):
        i = pi[a]
        j = pj[a]
        _union_back_neighbours(idx, parent, a, i, j, w)
    root = np.empty(n, dtype=np.int32)
    jmin = np.full(n, w, dtype=np.int32)
    jmax = np.full(n, -1, dtype=np.int32)
    imin = np.full(n, h, dtype=np.int32)
    imax = np.full(n, -1, dtype=np.int32)
    npx = np.zeros(n, dtype=np.int32)
    for a in range(n):
        r = _find(parent, a)
        root[a] = r
        npx[r] += 1
        i = pi[a]
        j = pj[a]
        # the extent, written out: pixels come in raster order, so a component's first pixel
        # has its lowest bin and its last the highest (2x faster than the _grow_box helper here)
        if imin[r] > i:
            imin[r] = i
        imax[r] = i
        if j < jmin[r]:
            jmin[r] = j
        if j > jmax[r]:
            jmax[r] = j
    kept = np.zeros(n, dtype=np.bool_)      # per root
    n_kept = 0
    for a in range(n):
        r = root[a]
        if r == a and (_is_wide(r, imin, imax, jmin, jmax, min_beams, min_bins)
                       or (min_pixels > 0 and npx[r] >= min_pixels)):
            kept[r] = True
    for a in range(n):
        if kept[root[a]]:
            n_kept += 1
    add = np.zeros(n, dtype=np.bool_)
    for _ in range(rounds):
        if n_kept == 0 or n_kept == n:
            break
        # near pairs are symmetric: scan the windows of the smaller of the two pixel sets
        from_kept = n_kept <= n - n_kept
        hit = False
        for a in range(n):
            if kept[root[a]] != from_kept or (not from_kept and add[root[a]]):
                continue
            i = pi[a]
            j = pj[a]
            for ii in range(max(i - 1, 0), min(i + 2, h)):
                for jj in range(max(j - gap, 0), min(j + gap + 1, w)):
                    b = idx[ii, jj]
                    if b >= 0 and kept[root[b]] != from_kept:
                        hit = True
                        if from_kept:
                            add[root[b]] = True
                        else:
                            add[root[a]] = True
                            break
                if hit and not from_kept and add[root[a]]:
                    break
        if not hit:
            break
        for a in range(n):
            r = root[a]
            if add[r]:
                if not kept[r]:
                    kept[r] = True
                add[r] = False
        n_kept = 0
        for a in range(n):
            if kept[root[a]]:
                n_kept += 1
    out = np.zeros((h, w), dtype=np.bool_)
    for a in range(n):
        if kept[root[a]]:
            out[pi[a], pj[a]] = True
        idx[pi[a], pj[a]] = -1
    return out


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
def level_counts(levels, n_levels):  # pragma: no cover - numba
    """``np.bincount(levels.ravel(), minlength=n_levels)`` as float64 (levels are non-negative)."""
    h, w = levels.shape
    top = n_levels
    for i in range(h):
        for j in range(w):
            if levels[i, j] >= top:
                top = levels[i, j] + 1
    # four interleaved partial histograms: runs of one level (the zeros) do not serialise
    part = np.zeros((4, top), dtype=np.int64)
    n = h * w
    flat = levels.ravel()
    n4 = n - n % 4
    for k in range(0, n4, 4):
        part[0, flat[k]] += 1
        part[1, flat[k + 1]] += 1
        part[2, flat[k + 2]] += 1
        part[3, flat[k + 3]] += 1
    for k in range(n4, n):
        part[0, flat[k]] += 1
    out = np.empty(top)
    for v in range(top):
        out[v] = float(part[0, v] + part[1, v] + part[2, v] + part[3, v])
    return out


@njit(cache=True, nogil=True)
def box_mean_f32(img, size0, size1):  # pragma: no cover - numba
    """``scipy.ndimage.uniform_filter(img, size=(size0, size1), mode="constant")`` of a 2-D float32
    image, bit for bit (scipy's arithmetic: axis 0 then axis 1, axes of size 1 skipped, each line
    zero-padded by ``size // 2`` before, a double running sum ``+= new - old`` divided by the size
    and rounded to float32; ``tests/test_pipeline.py`` checks the identity against scipy)."""
    h, w = img.shape
    mid = np.empty((h, w), dtype=np.float32)
    if size0 > 1:
        b0 = size0 // 2
        buf = np.zeros(h + size0 - 1)
        for j in range(w):
            for i in range(h):
                buf[b0 + i] = img[i, j]
            tmp = 0.0
            for k in range(size0):
                tmp += buf[k]
            mid[0, j] = tmp / size0
            for k in range(1, h):
                tmp += buf[k + size0 - 1] - buf[k - 1]
                mid[k, j] = tmp / size0
    else:
        mid[:, :] = img
    if size1 <= 1:
        return mid
    out = np.empty((h, w), dtype=np.float32)
    b1 = size1 // 2
    buf = np.zeros(w + size1 - 1)
    for i in range(h):
        for j in range(w):
            buf[b1 + j] = mid[i, j]
        tmp = 0.0
        for k in range(size1):
            tmp += buf[k]
        out[i, 0] = tmp / size1
        for k in range(1, w):
            tmp += buf[k + size1 - 1] - buf[k - 1]
            out[i, k] = tmp / size1
    return out


@njit(cache=True, nogil=True)
def band_peak_pixels(band, img, cols):  # pragma: no cover - numba
    """Band pooling's pick: on each beam ``j`` with ``cols[j]``, the strongest ``img`` pixel of
    the first run of ``band`` rows (first maximum on ties); returns a boolean image with one pixel
    per picked beam.  Same as the numpy formulation in :func:`sonarmap.pipeline.pooled_band_pixels`."""
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
