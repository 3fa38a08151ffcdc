"""OctoMap binary trees (``.bt``) from occupancy maps, for octovis, RViz and ``octomap_server``.

The ``.bt`` format (OctoMap's ``OcTree::writeBinary``) is a maximum-likelihood octree: every
known voxel is either *free* or *occupied*, everything else is unknown.  A file is a text header::

    # Octomap OcTree binary file
    id OcTree
    size <number of nodes, root included>
    res <voxel edge in metres>
    data

followed by the tree, depth first from the root: each inner node is 2 bytes holding 2 bits per
child, children 0-3 in the first byte and 4-7 in the second, child ``c`` in bits ``2c % 8`` and
``2c % 8 + 1``, as the field value ``bit0 + 2 bit1``: 0 unknown (no child), 1 free leaf,
2 occupied leaf, 3 inner node (its own 2 bytes follow, after those of the inner siblings before
it).  Child ``c`` of a node covers the octant ``c = x + 2 y + 4 z`` (bit set = the upper half).
The tree is 16 levels deep: voxel keys are ``floor(p / res) + 32768`` per axis, so the map's
local origin is OctoMap's origin and the representable extent is +-32768 voxels (+-1638 m at
5 cm).  Eight sibling leaves of one state are merged into their parent (OctoMap's pruning),
which is what ``writeBinary`` produces too.

Frames: ROS (RViz, ``octomap_server``) and octovis expect z up, so :func:`write_octomap_bt` writes
ENU by default: an NED voxel ``(i, j, k)`` (north, east, down) is the ENU voxel
``(j, i, -k - 1)`` - the same cube, so no resampling is involved.  The ``.bt`` format has no CRS:
the tree is in the local frame; with a :class:`~sonarmap.mapping.georef.GeoReference` its origin
is the georeference's origin.

Occupancy probabilities are reduced to OctoMap's maximum-likelihood states: a voxel is occupied
when its log-odds exceed the map's ``occupied_logodds`` (probability 0.5 by default), free when
it was observed and is not occupied; OctoMap reads occupied leaves back at its upper clamping
bound and free ones at its lower bound.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from sonarmap._atomic import atomic_write_bytes
from sonarmap.errors import DataFormatError, InputError
from sonarmap.mapping.frames import world_frame
from sonarmap.mapping.occupancy import OccupancyArray, OccupancyMap

__all__ = ["OcTreeFile", "OcTreeLeaves", "write_octomap_bt", "read_octomap_bt", "octomap_keys", "TREE_DEPTH"]

#: Levels of an OctoMap ``OcTree`` (keys are 16-bit per axis).
TREE_DEPTH = 16
#: The key of the cell whose minimum corner is the origin.
KEY_ORIGIN = 1 << (TREE_DEPTH - 1)
_HEADER = b"# Octomap OcTree binary file\n"
_FREE, _OCCUPIED, _INNER = 1, 2, 3


@dataclasses.dataclass(frozen=True)
class OcTreeFile:
    """What :func:`write_octomap_bt` wrote.

    Parameters
    ----------
    n_nodes : int
        Nodes in the tree, root included (the header's ``size``).
    n_leaves : int
        Leaves after pruning (each free or occupied).
    n_occupied_voxels, n_free_voxels : int
        Voxels at the map's resolution in each state (before pruning).
    resolution_m : float
    frame : str
        ``"enu"`` or ``"ned"``: the axes of the tree.
    """

    n_nodes: int
    n_leaves: int
    n_occupied_voxels: int
    n_free_voxels: int
    resolution_m: float
    frame: str


@dataclasses.dataclass(frozen=True, eq=False)
class OcTreeLeaves:
    """The leaves of a ``.bt`` file (see :func:`read_octomap_bt`).

    Parameters
    ----------
    key_min : ndarray, shape (n, 3), int64
        OctoMap key of each leaf's minimum voxel.
    size_voxels : ndarray, shape (n,), int64
        Leaf edge in voxels (1 at full depth, 2**m for a leaf m levels up).
    occupied : ndarray of bool, shape (n,)
    resolution_m : float
    n_nodes : int
        The header's ``size``.
    """

    key_min: NDArray[np.int64]
    size_voxels: NDArray[np.int64]
    occupied: NDArray[np.bool_]
    resolution_m: float
    n_nodes: int

    @property
    def centers_m(self) -> NDArray[np.float64]:
        """Leaf centres in metres (OctoMap's ``keyToCoord`` at the leaf's depth), shape (n, 3)."""
        k = (self.key_min - KEY_ORIGIN).astype(np.float64) + self.size_voxels[:, None] / 2.0
        return k * self.resolution_m

    def voxels(self, occupied: bool = True) -> NDArray[np.int64]:
        """Voxel indices ``floor(p / res)`` (n, 3) of every full-resolution voxel in that state."""
        sel = self.occupied == occupied
        keys, sizes = self.key_min[sel], self.size_voxels[sel]
        out = [keys[sizes == 1]]
        for s in np.unique(sizes[sizes > 1]):
            base = keys[sizes == s]
            g = np.stack(np.meshgrid(*(np.arange(s),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
            out.append((base[:, None, :] + g[None, :, :]).reshape(-1, 3))
        return np.concatenate(out).astype(np.int64) - KEY_ORIGIN


# ------------------------------------------------------------------------------ Morton codes
def _morton(keys: NDArray[np.int64]) -> NDArray[np.uint64]:
    """Interleave 16-bit keys so that ``(code >> 3 (15 - d)) & 7`` is the child index at depth ``d``."""
    k = keys.astype(np.uint64)
    code = np.zeros(k.shape[0], dtype=np.uint64)
    for b in range(TREE_DEPTH):
        sh = np.uint64(b)
        for axis in range(3):
            code |= ((k[:, axis] >> sh) & np.uint64(1)) << np.uint64(3 * b + axis)
    return code


def _unmorton(code: NDArray[np.uint64], n_bits: int) -> NDArray[np.int64]:
    """Per-axis integers of the low ``3 n_bits`` bits of a Morton code, shape (n, 3)."""
    out = np.zeros((code.shape[0], 3), dtype=np.uint64)
    for b in range(n_bits):
        for axis in range(3):
            out[:, axis] |= ((code >> np.uint64(3 * b + axis)) & np.uint64(1)) << np.uint64(b)
    return out.astype(np.int64)


# ------------------------------------------------------------------------------ writer
def octomap_keys(ijk: NDArray[np.int64], *, frame: str = "enu") -> NDArray[np.int64]:
    """OctoMap keys of NED voxel indices ``(i, j, k)``, shape (n, 3), in the tree's ``frame``.

    Raises
    ------
    InputError
        If a voxel is outside OctoMap's 16-bit key range.
    """
    fr = world_frame(frame)
    v = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    if fr == "enu":  # the NED cube [i, i+1) x [j, j+1) x [k, k+1) (N, E, D) is ENU [j, ..) x [i, ..) x [-k-1, -k)
        v = np.stack([v[:, 1], v[:, 0], -v[:, 2] - 1], axis=1)
    keys = v + KEY_ORIGIN
    if keys.size and (keys.min() < 0 or keys.max() >= 1 << TREE_DEPTH):
        raise InputError(
            f"occupancy_map: voxel indices reach {int(np.abs(v).max())}, beyond OctoMap's +-{KEY_ORIGIN} voxels; "
            "coarsen the resolution"
        )
    return keys


def _cells(occupancy_map: OccupancyMap | OccupancyArray, threshold_logodds: float | None) -> tuple[
    NDArray[np.int64], NDArray[np.bool_], float
]:
    """Observed voxel indices (n, 3), their occupied flags, and the resolution."""
    if isinstance(occupancy_map, OccupancyMap):
        cfg = occupancy_map.config
        if cfg.dims != 3:
            raise InputError("occupancy_map: an OctoMap needs a 3-D map (dims=3); write 2-D grids with write_geotiff")
        thr = cfg.occupied_logodds if threshold_logodds is None else float(threshold_logodds)
        ijk = occupancy_map.observed_cells()
        lo, _ = occupancy_map.logodds_at(occupancy_map.cell_centers(ijk))
        return ijk, lo > thr, float(cfg.resolution_m)
    if isinstance(occupancy_map, OccupancyArray):
        lo = np.asarray(occupancy_map.logodds)
        if lo.ndim != 3:
            raise InputError(f"occupancy_map: an OctoMap needs a 3-D array, got shape {lo.shape}")
        res = float(occupancy_map.resolution_m)
        thr = 0.0 if threshold_logodds is None else float(threshold_logodds)
        idx = np.argwhere(np.asarray(occupancy_map.observed, dtype=bool))
        base = np.rint(np.asarray(occupancy_map.origin_m, dtype=np.float64) / res).astype(np.int64)
        return idx + base, lo[tuple(idx.T)] > thr, res
    raise InputError(f"occupancy_map: expected an OccupancyMap or OccupancyArray, got {type(occupancy_map).__name__}")


def _tree_bytes(keys: NDArray[np.int64], occupied: NDArray[np.bool_]) -> tuple[bytes, int, int]:
    """The depth-first node stream, the node count (root included) and the number of leaves."""
    code = _morton(keys)
    order = np.argsort(code, kind="stable")
    code = code[order]
    value = np.where(occupied[order], _OCCUPIED, _FREE).astype(np.uint16)
    levels: dict[int, tuple[NDArray[np.uint64], NDArray[np.uint16]]] = {}
    for depth in range(TREE_DEPTH, 0, -1):
        parent = code >> np.uint64(3)
        starts = np.flatnonzero(np.r_[True, parent[1:] != parent[:-1]])
        counts = np.diff(np.r_[starts, parent.size])
        vmin = np.minimum.reduceat(value, starts)
        vmax = np.maximum.reduceat(value, starts)
        # eight leaves of one state collapse into their parent (never into the root)
        prune = (counts == 8) & (vmin == vmax) & (vmin != _INNER) & (depth > 1)
        keep = ~np.repeat(prune, counts)
        levels[depth] = (code[keep], value[keep])
        code = parent[starts]
        value = np.where(prune, vmin, _INNER).astype(np.uint16)
    # code is now [0]: the root.  Each inner node's 16-bit mask from its children's 2-bit values
    inner_code: list[NDArray[np.uint64]] = [np.zeros(1, np.uint64)]
    inner_depth: list[NDArray[np.int64]] = [np.zeros(1, np.int64)]
    masks: dict[int, NDArray[np.uint16]] = {}
    for depth in range(1, TREE_DEPTH + 1):
        c, v = levels[depth]
        parent = c >> np.uint64(3)
        starts = np.flatnonzero(np.r_[True, parent[1:] != parent[:-1]]) if c.size else np.zeros(0, np.int64)
        bits = (v.astype(np.uint32) << (2 * (c & np.uint64(7))).astype(np.uint32)).astype(np.uint32)
        masks[depth - 1] = np.add.reduceat(bits, starts).astype(np.uint16) if c.size else np.zeros(0, np.uint16)
        if depth < TREE_DEPTH:
            inner = c[v == _INNER]
            inner_code.append(inner)
            inner_depth.append(np.full(inner.size, depth, np.int64))
    # pre-order: by the node's first voxel (its code padded to full depth), ancestors first
    codes = np.concatenate(inner_code)
    depths = np.concatenate(inner_depth)
    padded = codes << (np.uint64(3) * (TREE_DEPTH - depths).astype(np.uint64))
    all_masks = np.concatenate([masks[d] for d in range(TREE_DEPTH)])  # same order: depth, then code
    pre = np.lexsort((depths, padded))
    n_nodes = 1 + sum(levels[d][0].size for d in range(1, TREE_DEPTH + 1))
    n_leaves = sum(int((levels[d][1] != _INNER).sum()) for d in range(1, TREE_DEPTH + 1))
    return all_masks[pre].astype("<u2").tobytes(), n_nodes, n_leaves


def write_octomap_bt(
    path: str | os.PathLike[str],
    occupancy_map: OccupancyMap | OccupancyArray,
    *,
    frame: str = "enu",
    threshold_logodds: float | None = None,
) -> OcTreeFile:
    """Write a 3-D occupancy map as an OctoMap binary tree (``.bt``), atomically.

    Parameters
    ----------
    path : path-like
    occupancy_map : OccupancyMap or OccupancyArray
        A 3-D map in the local NED frame (sonarmap's world frame).
    frame : {"enu", "ned"}
        Axes of the tree; ``"enu"`` (default) is what RViz, ``octomap_server`` and octovis
        expect (z up).
    threshold_logodds : float, optional
        Voxels above it are occupied (default the map's ``occupied_logodds``, 0 = p 0.5).

    Returns
    -------
    OcTreeFile

    Raises
    ------
    InputError
        For a 2-D map or one beyond OctoMap's +-32768-voxel extent.

    Examples
    --------
    >>> info = write_octomap_bt("map.bt", occupancy_map)   # doctest: +SKIP
    >>> info.n_occupied_voxels                             # doctest: +SKIP
    """
    ijk, occ, res = _cells(occupancy_map, threshold_logodds)
    keys = octomap_keys(ijk, frame=frame)
    if keys.shape[0]:
        data, n_nodes, n_leaves = _tree_bytes(keys, occ)
    else:
        data, n_nodes, n_leaves = b"", 0, 0  # OctoMap writes an empty tree as size 0 and no data
    head = _HEADER + (
        "# (feel free to add / change comments, but leave the first line as it is!)\n"
        f"# written by sonarmap: frame {str(frame).lower()}, origin = the map's local origin\n"
        f"id OcTree\nsize {n_nodes}\nres {res!r}\ndata\n"
    ).encode("ascii")
    atomic_write_bytes(path, head + data)
    return OcTreeFile(n_nodes, n_leaves, int(occ.sum()), int((~occ).sum()), res, str(frame).lower())


# ------------------------------------------------------------------------------ reader
def read_octomap_bt(path: str | os.PathLike[str]) -> OcTreeLeaves:
    """Read the leaves of an OctoMap ``.bt`` file (``id OcTree``).

    Raises
    ------
    DataFormatError
        If the header is not an OcTree binary header, or the node stream is truncated, has
        trailing bytes, or disagrees with the header's ``size``.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
    if not raw.startswith(_HEADER):
        raise DataFormatError("not an OctoMap binary tree (first line is not '# Octomap OcTree binary file')", p)
    pos, size, res = _read_bt_header(raw, p)
    data = raw[pos:]
    if size == 0:
        if data:
            raise DataFormatError("size 0 but data follows the header", p)
        z = np.zeros((0, 3), np.int64)
        return OcTreeLeaves(z, np.zeros(0, np.int64), np.zeros(0, bool), res, 0)
    if len(data) % 2:
        raise DataFormatError("odd number of bytes in the node stream", p, pos + len(data) - 1)
    leaves = _read_bt_nodes(np.frombuffer(data, dtype="<u2"), p, pos)
    if leaves.n_nodes != size:
        raise DataFormatError(f"the tree has {leaves.n_nodes} nodes, the header says {size}", p)
    codes = np.array(leaves.code, dtype=np.uint64)
    depths = np.array(leaves.depth, dtype=np.int64)
    key_min = np.zeros((codes.size, 3), np.int64)
    for d in np.unique(depths):
        sel = depths == d
        key_min[sel] = _unmorton(codes[sel], int(d)) << (TREE_DEPTH - int(d))
    return OcTreeLeaves(key_min, (1 << (TREE_DEPTH - depths)).astype(np.int64), np.array(leaves.occupied, dtype=bool),
                        res, leaves.n_nodes)


class _BtHeader(NamedTuple):
    """The text header of a ``.bt`` file."""

    data_offset: int
    """Byte offset of the node stream (after the ``data`` line)."""
    size: int
    """The header's ``size``: nodes in the tree, root included."""
    resolution_m: float
    """The header's ``res``."""


def _read_bt_header(raw: bytes, p: Path) -> _BtHeader:
    """The header of ``raw`` (the bytes of the ``.bt`` file ``p``), read after its first line up to
    ``data``; raises :class:`DataFormatError` without a ``data`` line or with a bad ``id``, ``size``
    or ``res``."""
    pos, tree_id, size, res = len(_HEADER), None, None, None
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise DataFormatError("header without a 'data' line", p)
        line = raw[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if line == "data":
            break
        if not line or line.startswith("#"):
            continue
        key, _, value = line.partition(" ")
        try:
            if key == "id":
                tree_id = value.strip()
            elif key == "size":
                size = int(value)
            elif key == "res":
                res = float(value)
        except ValueError:
            raise DataFormatError(f"bad header line {line!r}", p) from None
    if tree_id != "OcTree":
        raise DataFormatError(f"tree id {tree_id!r} is not 'OcTree'", p)
    if size is None or size < 0 or res is None or not (math.isfinite(res) and res > 0):
        raise DataFormatError(f"header needs size >= 0 and res > 0 (got {size}, {res})", p)
    return _BtHeader(pos, size, res)


class _BtLeaves(NamedTuple):
    """The leaves of a ``.bt`` node stream, in the stream's (depth-first) order."""

    code: list[int]
    """Each leaf's Morton code (3 bits per level below the root)."""
    depth: list[int]
    """Each leaf's depth (1 = a child of the root)."""
    occupied: list[bool]
    """Each leaf's state."""
    n_nodes: int
    """Nodes in the tree, root included."""


def _read_bt_nodes(masks: NDArray[np.uint16], p: Path, pos: int) -> _BtLeaves:
    """Walk the 16-bit child masks of a ``.bt`` node stream (at byte ``pos`` of file ``p``) from the
    root; raises :class:`DataFormatError` if the stream ends inside the tree, has an inner node at
    the deepest level, or has bytes after the tree."""
    leaf_code: list[int] = []
    leaf_depth: list[int] = []
    leaf_occ: list[bool] = []
    n_nodes, cursor = 1, 0
    stack: list[tuple[int, int]] = [(0, 0)]  # (code, depth) of inner nodes still to read, in pre-order
    while stack:
        node, depth = stack.pop()
        if cursor >= masks.size:
            raise DataFormatError("node stream ends inside the tree", p, pos + 2 * cursor)
        mask = int(masks[cursor])
        cursor += 1
        inner = []
        for c in range(8):
            v = (mask >> (2 * c)) & 3
            if v == 0:
                continue
            n_nodes += 1
            child = (node << 3) | c
            if v == _INNER:
                if depth + 1 >= TREE_DEPTH:
                    raise DataFormatError("inner node at the deepest level", p, pos + 2 * (cursor - 1))
                inner.append((child, depth + 1))
            else:
                leaf_code.append(child)
                leaf_depth.append(depth + 1)
                leaf_occ.append(v == _OCCUPIED)
        stack.extend(reversed(inner))
    if cursor != masks.size:
        raise DataFormatError(f"{2 * (masks.size - cursor)} bytes after the tree", p, pos + 2 * cursor)
    return _BtLeaves(leaf_code, leaf_depth, leaf_occ, n_nodes)
