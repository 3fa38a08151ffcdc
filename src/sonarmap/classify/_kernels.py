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


@njit(cache=True, nogil=True)
def level_cost_table(lp, prior, with_prior, floor):  # pragma: no cover - numba
    """The per-level cost table of :func:`sonarmap.classify.segment.level_costs`, elementwise as
    its numpy form computes it: ``v = lp[k, l] + prior[k]`` (without ``with_prior``: ``lp[k, l]``),
    NaN and ``-inf`` -> ``floor``, ``+inf`` -> 0, ``cost = -max(v, floor)``, less the level's
    least cost."""
    n_cls, n = lp.shape
    cost = np.empty((n_cls, n))
    for lev in range(n):
        low = np.inf
        for k in range(n_cls):
            v = lp[k, lev] + prior[k] if with_prior else lp[k, lev]
            if np.isnan(v) or v == -np.inf:
                v = floor
            elif v == np.inf:
                v = 0.0
            c = -(v if v > floor else floor)
            cost[k, lev] = c
            if c < low:
                low = c
        for k in range(n_cls):
            cost[k, lev] = cost[k, lev] - low
    return cost


@njit(cache=True, nogil=True, inline="always")
def _pairwise_block(a, lo, n):  # pragma: no cover - numba
    """numpy's float64 pairwise summation of ``a[lo:lo + n]`` for ``n <= 128``: a plain loop
    below 8 terms, else 8 interleaved partial sums combined as a tree, then the remainder."""
    if n < 8:
        res = 0.0
        for t in range(n):
            res += a[lo + t]
        return res
    r0 = a[lo]
    r1 = a[lo + 1]
    r2 = a[lo + 2]
    r3 = a[lo + 3]
    r4 = a[lo + 4]
    r5 = a[lo + 5]
    r6 = a[lo + 6]
    r7 = a[lo + 7]
    t = 8
    while t < n - n % 8:
        r0 += a[lo + t]
        r1 += a[lo + t + 1]
        r2 += a[lo + t + 2]
        r3 += a[lo + t + 3]
        r4 += a[lo + t + 4]
        r5 += a[lo + t + 5]
        r6 += a[lo + t + 6]
        r7 += a[lo + t + 7]
        t += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while t < n:
        res += a[lo + t]
        t += 1
    return res


@njit(cache=True, nogil=True)
def _pairwise_sum(a, lo, n):  # pragma: no cover - numba
    """``a[lo:lo + n].sum()`` exactly as numpy computes it for float64: pairwise summation,
    :func:`_pairwise_block` up to 128 terms, above that the sum of the two halves (the first
    half's length rounded down to a multiple of 8).  The recursion is unrolled into an explicit
    post-order traversal (numba does not cache recursive functions reliably)."""
    if n <= 128:
        return _pairwise_block(a, lo, n)
    f_lo = np.empty(64, dtype=np.int64)
    f_n = np.empty(64, dtype=np.int64)
    f_done = np.empty(64, dtype=np.bool_)
    vals = np.empty(64)
    f_lo[0] = lo
    f_n[0] = n
    f_done[0] = False
    top = 1
    nv = 0
    while top > 0:
        top -= 1
        s = f_lo[top]
        m = f_n[top]
        if m <= 128:
            vals[nv] = _pairwise_block(a, s, m)
            nv += 1
        elif f_done[top]:
            nv -= 1
            vals[nv - 1] = vals[nv - 1] + vals[nv]      # left half + right half
        else:
            m2 = m // 2
            m2 -= m2 % 8
            f_done[top] = True                        # combine after both halves
            f_lo[top + 1] = s + m2                    # right half, evaluated second
            f_n[top + 1] = m - m2
            f_done[top + 1] = False
            f_lo[top + 2] = s                         # left half, evaluated first
            f_n[top + 2] = m2
            f_done[top + 2] = False
            top += 3
    return vals[0]


@njit(cache=True, nogil=True)
def decision_rates_pmf(pmf, det, prior):  # pragma: no cover - numba
    """``(pd, pfa)`` of :func:`sonarmap.classify.segment.decision_pd_pfa` from the class pmfs
    ``(n_classes, n_levels)``, the detected levels and the class priors, with numpy's float64
    summation order (:func:`_pairwise_sum`) and Python's ``min`` / ``max``, so bit for bit its
    numpy form for two classes (with more, numpy's row sums of ``pmf[1:][:, det]`` are not
    pairwise per row): pFA the background's pmf summed over the detected levels, pD the object
    classes' sums weighted by their priors over the object prior."""
    n_cls, n = pmf.shape
    sel = np.empty(n)
    m = 0
    for lev in range(n):
        if det[lev]:
            sel[m] = pmf[0, lev]
            m += 1
    # (np.int64 arguments: the literal 0 and 1 and a counter that starts at a literal 0 would each
    # compile _pairwise_sum again for a Literal[int] argument)
    pfa = _pairwise_sum(sel, np.int64(0), np.int64(m))
    weighted = np.empty(n_cls - 1)
    for c in range(1, n_cls):
        m = 0
        for lev in range(n):
            if det[lev]:
                sel[m] = pmf[c, lev]
                m += 1
        weighted[c - 1] = _pairwise_sum(sel, np.int64(0), np.int64(m)) * prior[c]
    den = _pairwise_sum(prior, np.int64(1), n_cls - 1)
    pd = _pairwise_sum(weighted, np.int64(0), n_cls - 1) / (1e-300 if 1e-300 > den else den)
    return (1.0 if 1.0 < pd else pd), (1.0 if 1.0 < pfa else pfa)


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


@njit(cache=True, nogil=True, inline="always")
def _pass1_pixel(levels, margin_lut, weights, wtot, fixed, stack, i, j, n_left):  # pragma: no cover
    """The first-pass test of one pixel with any weights (:func:`reduce_binary`): the unconditional
    ``|margin| > wtot``, else the test with the already-visited neighbours' states (the others
    count as free); appends the pixel to ``stack`` when it stays free and returns the new count."""
    h, w = levels.shape
    mm = margin_lut[levels[i, j]]
    t = wtot[i, j]
    if mm > t:
        fixed[i, j] = 1
        return n_left
    if mm < -t:
        fixed[i, j] = 0
        return n_left
    wf = 0.0
    for d in range(weights.shape[0]):
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
        stack[n_left] = i * w + j
        n_left += 1
    return n_left


@njit(cache=True, nogil=True)
def reduce_binary(levels, margin_lut, weights, wtot, fixed, stack, uniform, max_sweeps=256):  # pragma: no cover
    """Exact persistency reduction of a binary Potts problem; lists the pixels left free.

    The margin of pixel ``(i, j)`` is ``margin_lut[levels[i, j]]`` (``unary[0] - unary[1]``,
    positive favours label 1); a general unary is passed as ``levels = arange(h*w)`` and
    ``margin_lut = margin.ravel()``.  ``wtot`` is the total incident edge weight per pixel;
    ``fixed`` and ``stack`` (``h * w`` entries) are caller-owned work arrays (reused
    across pings of equal shape, so no large allocation happens per call).

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
        Pixels left free: ``fixed`` holds 0/1, or -1 for free pixels; ``stack[:n_free]`` lists the
        free pixels' flat indices in ascending raster order (see :func:`free_graph`).
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
            if not (uni and i > 0 and j > 0 and i < h - 1 and j < w - 1):
                n_left = _pass1_pixel(levels, margin_lut, weights, wtot, fixed, stack, i, j, n_left)
                continue
            mm = margin_lut[levels[i, j]]
            t = wtot[i, j]
            if mm > t:
                fixed[i, j] = 1
                continue
            if mm < -t:
                fixed[i, j] = 0
                continue
            wf = wr + wb
            a, mm = _pull(fixed[i - 1, j], wr, mm)
            wf += a
            a, mm = _pull(fixed[i, j - 1], wb, mm)
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
        step = 1 if sweep % 2 == 1 else -1       # forward on odd sweeps, else backward
        k_out = lo if step == 1 else hi - 1
        k = k_out
        for _ in range(hi - lo):
            p = stack[k]
            i = p // w
            j = p - i * w
            if _try_fix_u(levels, margin_lut, weights, fixed, i, j, h, w, wr, wb) if uni else \
                    _try_fix(levels, margin_lut, weights, fixed, i, j, h, w):
                changed += 1
            else:
                stack[k_out] = p
                k_out += step
            k += step
        if step == 1:
            hi = k_out
        else:
            lo = k_out + 1
        sweep += 1
    # move the survivors (ascending raster order) to the front
    n_free = hi - lo
    for a in range(n_free):
        stack[a] = stack[lo + a]
    return n_free


@njit(cache=True, nogil=True)
def pass1_table(margin_lut, wr, wb, t):  # pragma: no cover - numba
    """The outcome of :func:`reduce_binary`'s first pass at an interior pixel of a uniform
    4-neighbourhood (``wr`` along range, ``wb`` across beams, total incident weight ``t``) for
    every level and state of its two visited neighbours, packed: entry ``3 l + up + 1`` holds, in
    its 3-bit field at bit ``3 (left + 1)``, ``3 (state + 1)`` of a pixel of level ``l`` whose upper
    neighbour has state ``up`` and left neighbour ``left`` (``-1`` free, 0, 1): a field's value is
    the shift of the next pixel's field.  Same arithmetic, in the same order, as the pixel test,
    so the table's decisions are the test's."""
    n = margin_lut.size
    tab = np.empty(3 * n, dtype=np.uint16)
    for lev in range(n):
        m0 = margin_lut[lev]
        for up in range(3):
            entry = 0
            for left in range(3):
                r = 0
                if m0 > t:
                    r = 1
                elif not m0 < -t:
                    wf = wr + wb
                    a, mm = _pull(up - 1, wr, m0)
                    wf += a
                    a, mm = _pull(left - 1, wb, mm)
                    wf += a
                    r = 1 if mm > wf else (0 if mm < -wf else -1)
                entry |= (3 * (r + 1)) << (3 * left)
            tab[3 * lev + up] = entry
    return tab


@njit(cache=True, nogil=True)
def reduce_uniform4(levels, margin_lut, weights, wtot, fixed, stack, wr, wb):  # pragma: no cover - numba
    """The first pass of :func:`reduce_binary` (``max_sweeps=0``) for uniform 4-neighbourhood
    weights (``wr`` along range, ``wb`` across beams; at least 3 x 3 pixels): the same fixed pixels
    and the same free list, faster.  An interior pixel's outcome is a function of its level and of
    the states of its upper and left neighbours (:func:`pass1_table`), so the raster sweep is one
    table read per pixel with a short dependency on the left neighbour's state; border pixels
    take the general test (:func:`_pass1_pixel`), whose outcome on the first and last pixel of
    the interior rows is kept per level and neighbour states when first met.  Returns ``n_free``."""
    h, w = levels.shape
    tab = pass1_table(margin_lut, wr, wb, wtot[1, 1])
    states = np.array([-1, 0, 0, 0, 0, 0, 1, 0], dtype=np.int8)  # state by field value 3 (state + 1)
    # the first and last pixel of an interior row: the general test's outcome is likewise a
    # function of the level and the visited neighbours' states (uniform weights: the same weights
    # and total on every interior row), kept when first met (-2: not yet) - on a tall image the
    # general test's unpredictable branches on these 2 pixels a row cost a third of the pass
    seen_first = np.full(3 * margin_lut.size, -2, dtype=np.int8)
    seen_last = np.full(9 * margin_lut.size, -2, dtype=np.int8)
    flat_levels = levels.reshape(h * w)
    flat_fixed = fixed.reshape(h * w)
    n = 0
    for j in range(w):
        n = _pass1_pixel(levels, margin_lut, weights, wtot, fixed, stack, 0, j, n)
    for i in range(1, h - 1):
        key = 3 * np.int64(levels[i, 0]) + np.int64(fixed[i - 1, 0]) + 1
        s = np.int64(seen_first[key])
        if s == -2:
            n = _pass1_pixel(levels, margin_lut, weights, wtot, fixed, stack, i, 0, n)
            s = np.int64(fixed[i, 0])
            seen_first[key] = s
        else:
            fixed[i, 0] = s
            if s < 0:
                stack[n] = i * w
                n += 1
        base = i * w
        # (unsigned indices into flat views: no negative-index wraparound code in the loop)
        row = np.uint64(base)
        up = np.uint64(base - w)
        # the left neighbour's state as the shift of its field in the table entry, 3 (s + 1): the
        # chain from one pixel's state to the next is a shift and a mask
        u = np.uint64(3 * (s + 1))
        for j in range(np.uint64(1), np.uint64(w - 1)):
            u = (np.uint64(tab[np.uint64(3 * np.int64(flat_levels[row + j]) + np.int64(flat_fixed[up + j]) + 1)])
                 >> u) & np.uint64(7)
            flat_fixed[row + j] = states[u]
            if u == 0:                         # free pixels come in runs: a predictable branch
                stack[np.uint64(n)] = row + j
                n += 1
        s = np.int64(states[u])
        key = 3 * (3 * np.int64(levels[i, w - 1]) + np.int64(fixed[i - 1, w - 1]) + 1) + s + 1
        s = np.int64(seen_last[key])
        if s == -2:
            n = _pass1_pixel(levels, margin_lut, weights, wtot, fixed, stack, i, w - 1, n)
            seen_last[key] = fixed[i, w - 1]
        else:
            fixed[i, w - 1] = s
            if s < 0:
                stack[n] = base + w - 1
                n += 1
    for j in range(w):
        n = _pass1_pixel(levels, margin_lut, weights, wtot, fixed, stack, h - 1, j, n)
    return n


@njit(cache=True, nogil=True, inline="always")
def _run_forward(flat_levels, margin_lut, flat_fixed, stack, k, n_free, w, up, down, tc, tv, wb,
                 buf):  # pragma: no cover - numba
    """The forward half of deciding the free run of one range bin that starts at ``stack[k]``
    (its pixels are the consecutive entries of ``stack`` in the bin): ``(n, tol)``, its length
    and the rounding bound of its decisions (:func:`_run_backward` makes them).

    Margins: given every pixel outside the run, the effective margins lie in ``[ulo, uhi]``
    (``buf[0]`` / ``buf[1]``): fixed neighbours add ``+w`` (label 1) or ``-w`` (label 0), a free
    neighbour in an adjacent bin anything in ``[-wr, wr]`` (``tc`` and ``tv`` map a neighbour
    state ``fixed + 1`` to its fixed contribution and its free weight; ``up`` / ``down``: the
    bin has a bin above / below).

    Min-marginals of the two chain problems (margins ``ulo`` / ``uhi``, Potts weight ``wb``) by
    forward-backward dynamic programming on message differences, computed in the same loop as the
    margins: with ``F_t`` / ``B_t`` the least cost of the chain before / after ``t`` given
    ``x_t``, ``F_t(1) - F_t(0) = clip(F_{t-1}(1) - F_{t-1}(0), -wb, wb) - u_t`` (kept in
    ``buf[2]`` / ``buf[3]``) and likewise backwards.  ``tol = 2e-15 n s`` bounds the DP's
    rounding error, ``s`` an upper bound on ``sum |ulo| + |uhi| + 2 wb`` over the run (the scale
    of the chain costs).  The run ends where the next entry of ``stack`` is not the next pixel
    of the bin, found in the same loop (one unpredictable loop exit per run)."""
    p0 = stack[k]
    j0 = p0 % w
    e0 = 0.0
    if j0 > 0:
        e0 = wb if flat_fixed[p0 - 1] == 1 else -wb
    scale = 0.0
    fl = 0.0
    fh = 0.0
    t = 0
    last = False
    while not last:
        p = p0 + t
        base = margin_lut[flat_levels[p]]
        vf = 0.0
        if up:
            f = np.uint64(flat_fixed[p - w] + 1)  # (unsigned: no wraparound code)
            base += tc[f]
            vf += tv[f]
        if down:
            f = np.uint64(flat_fixed[p + w] + 1)
            base += tc[f]
            vf += tv[f]
        lo = base - vf
        hi = base + vf
        scale += abs(base) + vf + wb
        inside = j0 + t + 1 < w
        last = not (inside and k + t + 1 < n_free and stack[k + t + 1] == p + 1)
        if t == 0:
            lo += e0
            hi += e0
            fl = -lo
            fh = -hi
        if last and inside:
            e1 = wb if flat_fixed[p + 1] == 1 else -wb
            lo += e1
            hi += e1
            if t == 0:
                fl = -lo
                fh = -hi
        if t > 0:
            fl = min(max(fl, -wb), wb) - lo
            fh = min(max(fh, -wb), wb) - hi
        buf[0, t] = lo
        buf[1, t] = hi
        buf[2, t] = fl
        buf[3, t] = fh
        t += 1
    return t, 2e-15 * t * (2.0 * scale)


@njit(cache=True, nogil=True, inline="always")
def _run_backward(flat_fixed, p0, n, wb, tol, buf):  # pragma: no cover - numba
    """The backward half of :func:`_run_forward`'s run ``p0 .. p0 + n - 1``: each pixel's state
    into ``flat_fixed``, 1 where label 1 is cheaper by more than ``tol`` under ``ulo`` (every
    minimiser has 1), 0 where label 0 is under ``uhi``, else -1 (``x_t = 1`` beats ``x_t = 0`` by
    ``-(F_t(1) - F_t(0) + B_t(1) - B_t(0))``); whether it fixed a pixel."""
    bl = 0.0
    bh = 0.0
    hit = False
    for t in range(n - 1, -1, -1):
        # branch-free: at most one of the two tests holds (the margins satisfy ulo <= uhi)
        d = -1 + 2 * (buf[2, t] + bl < -tol) + (buf[3, t] + bh > tol)
        flat_fixed[p0 + t] = d
        hit |= d >= 0
        bl = min(max(bl - buf[0, t], -wb), wb)
        bh = min(max(bh - buf[1, t], -wb), wb)
    return hit


@njit(cache=True, nogil=True)
def reduce_chains(levels, margin_lut, fixed, stack, n_free, wr, wb, max_passes):  # pragma: no cover - numba
    """Exact persistency reduction by chains along the beams, after :func:`reduce_binary`
    (uniform 4-neighbourhood weights: ``wr`` along range, ``wb`` across beams).

    Each maximal run of free pixels in one range bin is a chain; with everything outside it held
    fixed, its effective margins lie between ``ulo`` and ``uhi`` (a free neighbour in an adjacent
    bin contributes anything in ``[-wr, wr]``; :func:`_run_forward`).  For a submodular energy
    the least minimiser grows with the margins, so a pixel that takes label 1 in every minimiser
    of the chain under ``ulo`` has 1 in every minimiser of the whole problem, and one that takes 0
    in every minimiser under ``uhi`` has 0 (the restriction of a minimiser to the chain minimises
    the chain problem with the true margins).  The chain min-marginals are exact dynamic
    programming (:func:`_run_forward`, :func:`_run_backward`); a decision needs a min-marginal gap
    above a bound on the DP's rounding error, so the fixing is exact in floating point too.  Since
    the Potts weight across beams is the strong one, this decides most of what the single-pixel
    test of :func:`reduce_binary` leaves.  Passes over the remaining list ``stack[:n_free]``
    (which must be in ascending raster order, kept while compacting it after each pass) repeat
    until one fixes nothing or ``max_passes`` have run; a pass skips a bin whose own and adjacent
    bins have not changed since its last evaluation.  Returns the new ``n_free``.
    """
    h, w = levels.shape
    buf = np.empty((4, w))
    tc = np.array([0.0, -wr, wr])              # by neighbour state + 1: free, fixed 0, fixed 1
    tv = np.array([wr, 0.0, 0.0])
    flat_levels = levels.reshape(h * w)
    flat_fixed = fixed.reshape(h * w)
    # a row's runs are evaluated again only if a pixel of the row or of an adjacent row has been
    # fixed since its last evaluation: row r was last evaluated at stamp ev[r] and last changed
    # at ch[r + 1] (ch is padded by one row on each side)
    ev = np.full(h, -1, dtype=np.int64)
    ch = np.zeros(h + 2, dtype=np.int64)
    stamp = 0
    for _ in range(max_passes):
        k = 0
        changed = False
        while k < n_free:
            i = stack[k] // w
            end = (i + 1) * w
            e = ev[i]
            if e >= 0 and ch[i] < e and ch[i + 1] < e and ch[i + 2] < e:
                while k < n_free and stack[k] < end:  # nothing new around: the row's runs stay
                    k += 1
                continue
            stamp += 1
            ev[i] = stamp
            hit = False
            while k < n_free and stack[k] < end:
                n, tol = _run_forward(flat_levels, margin_lut, flat_fixed, stack, k, n_free, w, i > 0, i < h - 1,
                                      tc, tv, wb, buf)
                hit |= _run_backward(flat_fixed, stack[k], n, wb, tol, buf)
                k += n
            if hit:
                ch[i + 1] = ev[i]
                changed = True
        if not changed:
            break
        k_out = 0
        for k in range(n_free):                    # the survivors (-1), in ascending order
            p = stack[k]
            stack[k_out] = p
            k_out += flat_fixed[p] < 0
        n_free = k_out
    return n_free


@njit(cache=True, nogil=True)
def free_graph(levels, margin_lut, weights, fixed, node, stack, n_free):  # pragma: no cover - numba
    """The cut graph of the pixels the reductions left free.

    ``stack[:n_free]`` are the free pixels (flat indices, ascending); node ``a`` is pixel
    ``stack[a]``, and ``node[i, j]`` is set to the node of each free pixel.

    Returns
    -------
    m_eff : float64 (n_free,)
        Effective margin of each node: its own plus ``+w`` for every edge to a neighbour fixed to
        1 and ``-w`` for one fixed to 0.
    ei, ej : int64 (n_edges,), ew : float64 (n_edges,)
        Free-free edges (node indices) and their weights.
    """
    h, w = levels.shape
    n_dirs = weights.shape[0]
    for a in range(n_free):
        p = stack[a]
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
    return m_eff, ei[:n_edges], ej[:n_edges], ew[:n_edges]


@njit(cache=True, nogil=True, inline="always")
def _pull_fixed(f, wt, mm):  # pragma: no cover - numba
    """``mm`` plus ``wt`` for a neighbour fixed to 1, minus ``wt`` for one fixed to 0 (``f`` -1, a
    free neighbour: ``mm``)."""
    if f == 1:
        return mm + wt
    if f == 0:
        return mm - wt
    return mm


@njit(cache=True, nogil=True, inline="always")
def _add_edge(ei, ej, ew, n_edges, a, b, wt):  # pragma: no cover - numba
    """Append the edge ``(a, b)`` of weight ``wt``; returns the new edge count."""
    ei[n_edges] = a
    ej[n_edges] = b
    ew[n_edges] = wt
    return n_edges + 1


@njit(cache=True, nogil=True)
def free_graph4(levels, margin_lut, fixed, stack, n_free, wr, wb):  # pragma: no cover - numba
    """:func:`free_graph` for uniform 4-neighbourhood weights (``wr`` on every edge along range,
    ``wb`` on every edge across beams, as :func:`sonarmap.classify.mrf._uniform` makes them):
    the same arrays, without reading the weight array or the lattice-sized ``node`` map.  The
    free pixels are listed in ascending raster order, so a free right neighbour is the next node
    and the free lower neighbours are met in ascending order too: one pointer walking the list
    finds them (on a tall image the map's scattered writes and reads, and those of the weights,
    miss the cache at almost every node)."""
    h, w = levels.shape
    m_eff = np.empty(n_free)
    ei = np.empty(n_free * 2, dtype=np.int64)
    ej = np.empty(n_free * 2, dtype=np.int64)
    ew = np.empty(n_free * 2)
    n_edges = 0
    below = 0                                   # the node of the last free lower neighbour found
    for a in range(n_free):
        p = stack[a]
        i = p // w
        j = p - i * w
        mm = margin_lut[levels[i, j]]
        # the order of free_graph: down, up, right, left (the same sums, bit for bit)
        if i + 1 < h:
            f = fixed[i + 1, j]
            if f < 0 and wr != 0.0:
                while below < n_free - 1 and stack[below] < p + w:
                    below += 1
                n_edges = _add_edge(ei, ej, ew, n_edges, a, below, wr)
            mm = _pull_fixed(f, wr, mm)
        if i > 0:
            mm = _pull_fixed(fixed[i - 1, j], wr, mm)
        if j + 1 < w:
            f = fixed[i, j + 1]
            if f < 0 and wb != 0.0:
                n_edges = _add_edge(ei, ej, ew, n_edges, a, a + 1, wb)
            mm = _pull_fixed(f, wb, mm)
        if j > 0:
            mm = _pull_fixed(fixed[i, j - 1], wb, mm)
        m_eff[a] = mm
    return m_eff, ei[:n_edges], ej[:n_edges], ew[:n_edges]


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
