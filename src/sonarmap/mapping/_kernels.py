"""Numba kernels of the occupancy map: hashed voxel chunks and Amanatides-Woo ray traversal.

Storage (owned by :class:`sonarmap.mapping.occupancy.OccupancyMap`)
-------------------------------------------------------------------
* Space is cut into chunks of ``2**sx x 2**sy x 2**sz`` voxels (``sz = 0`` for a 2-D grid).
* ``keys`` / ``slots``: an open-addressing hash table (linear probing, capacity a power of two)
  from the packed chunk key ``((cx + 2**20) << 42) | ((cy + 2**20) << 21) | (cz + 2**20)`` to the
  chunk's row in the pool; ``EMPTY`` marks free table entries.
* ``logodds`` (float32) and ``stamp`` (int32) are flat pools of ``max_chunks * chunk_volume``
  voxels; ``stamp`` holds the id of the last ping that updated the voxel (0 = never observed), so
  each ping updates each voxel at most once and a hit in any beam overrides misses of other beams.
* ``counts[0]`` is the number of chunks in use.

Kernels return ``-1`` on success, or the index of the first ping they could not finish because
the pool or the table is full (the caller grows the storage and resumes from that ping - re-running
a ping is harmless because voxels it already updated carry its stamp), or ``-2`` if a coordinate
is outside the packable range (+-2**20 chunks).
"""

from __future__ import annotations

import numpy as np
from numba import njit

EMPTY = np.int64(-1)
_OFF = 1 << 20
_MASK21 = (1 << 21) - 1


@njit(cache=True, inline="always")
def _pack(cx: int, cy: int, cz: int) -> int:
    return ((cx + _OFF) << 42) | ((cy + _OFF) << 21) | (cz + _OFF)


@njit(cache=True)
def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """Chunk coordinates (n, 3) of packed keys."""
    out = np.empty((keys.size, 3), dtype=np.int64)
    for i in range(keys.size):
        k = keys[i]
        out[i, 0] = ((k >> 42) & _MASK21) - _OFF
        out[i, 1] = ((k >> 21) & _MASK21) - _OFF
        out[i, 2] = (k & _MASK21) - _OFF
    return out


@njit(cache=True, inline="always")
def _hash(key: int, mask: int) -> int:
    h = np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
    return int(h >> np.uint64(33)) & mask


@njit(cache=True, inline="always")
def _probe(keys: np.ndarray, key: int) -> int:
    """Entry of ``key`` in the table, or the free entry where it would go (linear probing)."""
    mask = keys.size - 1
    i = _hash(key, mask)
    while True:
        k = keys[i]
        if k == key or k == EMPTY:
            return i
        i = (i + 1) & mask


@njit(cache=True)
def _find(keys: np.ndarray, slots: np.ndarray, key: int) -> int:
    i = _probe(keys, key)
    if keys[i] == key:
        return slots[i]
    return -1


@njit(cache=True)
def _find_or_insert(keys: np.ndarray, slots: np.ndarray, chunk_keys: np.ndarray, counts: np.ndarray, key: int) -> int:
    i = _probe(keys, key)
    if keys[i] == key:
        return slots[i]
    n = counts[0]
    if n >= chunk_keys.size or 2 * (n + 1) > keys.size:
        return -1
    keys[i] = key
    slots[i] = n
    chunk_keys[n] = key
    counts[0] = n + 1
    return n


@njit(cache=True)
def rebuild_table(chunk_keys: np.ndarray, n: int, capacity: int) -> tuple[np.ndarray, np.ndarray]:
    """A fresh hash table of ``capacity`` entries holding the first ``n`` chunk keys."""
    keys = np.full(capacity, EMPTY, dtype=np.int64)
    slots = np.zeros(capacity, dtype=np.int32)
    for s in range(n):
        key = chunk_keys[s]
        i = _probe(keys, key)  # the keys are distinct: a free entry
        keys[i] = key
        slots[i] = s
    return keys, slots



@njit(cache=True, nogil=True)
def _axis_step(p, d, i):  # pragma: no cover - numba
    """Amanatides-Woo set-up for one axis of a ray starting at ``p`` (in cells) in cell ``i`` with
    direction component ``d``: (step, parameter distance per cell, parameter to the first boundary)."""
    if d > 0:
        return 1, 1.0 / d, (i + 1 - p) / d
    if d < 0:
        return -1, -1.0 / d, (p - i) / -d
    return 0, np.inf, np.inf


@njit(cache=True, inline="always")
def _voxel_index(c: int, ix: int, iy: int, iz: int, sx: int, sy: int, sz: int) -> int:  # pragma: no cover - numba
    """Position in the ``logodds`` / ``stamp`` pools of voxel ``(ix, iy, iz)`` of pool chunk ``c``
    (chunks of ``2**sx x 2**sy x 2**sz`` voxels)."""
    mx, my, mz = (1 << sx) - 1, (1 << sy) - 1, (1 << sz) - 1
    return (c << (sx + sy + sz)) | ((ix & mx) << (sy + sz)) | ((iy & my) << sz) | (iz & mz)


@njit(cache=True, inline="always")
def _packable(x: float, y: float, z: float, sx: int, sy: int, sz: int) -> bool:  # pragma: no cover - numba
    """Whether the chunk of the voxel holding point ``(x, y, z)`` (voxel units) has a packable key
    (+-2**20 chunks, less one of margin)."""
    lim = _OFF - 1
    return (abs(int(np.floor(x)) >> sx) < lim and abs(int(np.floor(y)) >> sy) < lim
            and abs(int(np.floor(z)) >> sz) < lim)


@njit(cache=True, inline="always")
def _add_segment(
    px: float, py: float, pz: float, qx: float, qy: float, qz: float, dl: float, pid: int,
    sx: int, sy: int, sz: int, l_min: float, l_max: float, last_key: int, last_c: int,
    keys: np.ndarray, slots: np.ndarray, chunk_keys: np.ndarray, counts: np.ndarray,
    logodds: np.ndarray, stamp: np.ndarray,
) -> tuple[int, int]:  # pragma: no cover - numba
    """Add ``dl`` to the log-odds of every voxel the segment from ``p`` to ``q`` (voxel units)
    crosses, ``p``'s voxel first and ``q``'s last (Amanatides & Woo 1987; ``p == q``: its one
    voxel), clamped to ``[l_min, l_max]``; a voxel ping ``pid`` already updated is left alone.

    ``(last_key, last_c)`` is the packed key and pool row of the chunk last updated (a walk stays
    in one chunk for many voxels: the table is probed only when the chunk changes); returns it
    after the segment, with a negative row if the pool or the table filled up on the way.  The
    caller has checked that both end voxels are inside the packable extent.
    """
    dx, dy, dz = qx - px, qy - py, qz - pz
    ix = int(np.floor(px))
    iy = int(np.floor(py))
    iz = int(np.floor(pz))
    n_steps = abs(int(np.floor(qx)) - ix) + abs(int(np.floor(qy)) - iy) + abs(int(np.floor(qz)) - iz)
    stx, tdx, tmx = _axis_step(px, dx, ix)
    sty, tdy, tmy = _axis_step(py, dy, iy)
    stz, tdz, tmz = _axis_step(pz, dz, iz)
    for _ in range(n_steps + 1):
        key = _pack(ix >> sx, iy >> sy, iz >> sz)
        if key != last_key:
            c = _find_or_insert(keys, slots, chunk_keys, counts, key)
            if c < 0:
                return last_key, c
            last_key = key
            last_c = c
        idx = _voxel_index(last_c, ix, iy, iz, sx, sy, sz)
        if stamp[idx] != pid:
            stamp[idx] = pid
            v = logodds[idx] + dl
            logodds[idx] = min(max(v, l_min), l_max)
        if tmx < tmy:
            if tmx < tmz:
                ix += stx
                tmx += tdx
            else:
                iz += stz
                tmz += tdz
        elif tmy < tmz:
            iy += sty
            tmy += tdy
        else:
            iz += stz
            tmz += tdz
    return last_key, last_c


@njit(cache=True)
def integrate_rays(
    starts: np.ndarray,  # (n_rays, 3) float64, voxel units (world / resolution)
    ends: np.ndarray,  # (n_rays, 3) float64, voxel units
    hit: np.ndarray,  # (n_rays,) bool: the ray ends on a return
    ray_offsets: np.ndarray,  # (n_pings + 1,) int64: rays of ping p are [off[p], off[p+1])
    l_hit: np.ndarray,  # (n_rays,) float32: added to the cell holding the ray's return
    l_miss: np.ndarray,  # (n_rays,) float32: added to the cells the ray crosses before it
    ping_ids: np.ndarray,  # (n_pings,) int32, > 0 and increasing
    first_ping: int,
    shifts: np.ndarray,  # (3,) int64 chunk shifts
    l_min: float,
    l_max: float,
    keys: np.ndarray,
    slots: np.ndarray,
    chunk_keys: np.ndarray,
    counts: np.ndarray,
    logodds: np.ndarray,
    stamp: np.ndarray,
) -> int:
    """Integrate pings ``first_ping ...``: hits first, then free space along every ray."""
    sx, sy, sz = shifts[0], shifts[1], shifts[2]
    n_pings = ray_offsets.size - 1
    for p in range(first_ping, n_pings):
        pid = ping_ids[p]
        r0 = ray_offsets[p]
        r1 = ray_offsets[p + 1]
        last_key = EMPTY
        last_c = -1
        # ---- pass 1: occupied updates at the returns
        for r in range(r0, r1):
            if not hit[r]:
                continue
            ex, ey, ez = ends[r, 0], ends[r, 1], ends[r, 2]
            if not _packable(ex, ey, ez, sx, sy, sz):
                return -2
            last_key, last_c = _add_segment(ex, ey, ez, ex, ey, ez, l_hit[r], pid, sx, sy, sz, l_min, l_max,
                                            last_key, last_c, keys, slots, chunk_keys, counts, logodds, stamp)
            if last_c < 0:
                return p
        # ---- pass 2: free space along each ray
        for r in range(r0, r1):
            px, py, pz = starts[r, 0], starts[r, 1], starts[r, 2]
            ex, ey, ez = ends[r, 0], ends[r, 1], ends[r, 2]
            # the walk stays between its end voxels (a voxel past them at most, inside the
            # margin of lim): checking both ends keeps every chunk it visits packable.  (Checked
            # in the walk only when the key changed, an unpackable first chunk whose key aliased
            # the last one - EMPTY itself for cz = -2**20 - 1 - was written at a negative row.)
            if not (_packable(px, py, pz, sx, sy, sz) and _packable(ex, ey, ez, sx, sy, sz)):
                return -2
            last_key, last_c = _add_segment(px, py, pz, ex, ey, ez, l_miss[r], pid, sx, sy, sz, l_min, l_max,
                                            last_key, last_c, keys, slots, chunk_keys, counts, logodds, stamp)
            if last_c < 0:
                return p
    return -1


@njit(cache=True)
def lookup(
    ijk: np.ndarray,  # (n, 3) int64 voxel indices
    shifts: np.ndarray,
    keys: np.ndarray,
    slots: np.ndarray,
    logodds: np.ndarray,
    stamp: np.ndarray,
    out_l: np.ndarray,  # (n,) float32
    out_seen: np.ndarray,  # (n,) bool
) -> None:
    """Log-odds and observed flag of voxels (0 / False where never observed)."""
    sx, sy, sz = shifts[0], shifts[1], shifts[2]
    lim = _OFF - 1
    for i in range(ijk.shape[0]):
        ix, iy, iz = ijk[i, 0], ijk[i, 1], ijk[i, 2]
        cx, cy, cz = ix >> sx, iy >> sy, iz >> sz
        out_l[i] = 0.0
        out_seen[i] = False
        if abs(cx) >= lim or abs(cy) >= lim or abs(cz) >= lim:
            continue
        c = _find(keys, slots, _pack(cx, cy, cz))
        if c < 0:
            continue
        idx = _voxel_index(c, ix, iy, iz, sx, sy, sz)
        out_l[i] = logodds[idx]
        out_seen[i] = stamp[idx] != 0
