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
