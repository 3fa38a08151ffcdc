"""Chunk files: the codecs, and the two chunk writers of product stores (zarr's API and direct,
atomic writes) - the same bytes either way, and never into a store replaced since."""

from __future__ import annotations

import os
import shutil
import types
from pathlib import Path

import numpy as np
import pytest

from sonarmap.store.chunks import ChunkRows, ChunkWriter, StoreReplacedError, array_codec_kwargs, chunk_key


def test_chunk_writer_writes_the_bytes_zarr_writes(tmp_path: Path) -> None:
    """Chunk files encoded by the live appender's writer are byte-identical to zarr's own (full and edge
    chunks, numeric and string variables, NaN fills) and read back through zarr unchanged."""
    import zarr

    rng = np.random.default_rng(1)
    n, k = 10, 4
    values = {
        "f": rng.random((n, 3)).astype(np.float32),
        "d": np.where(rng.random(n) < 0.3, np.nan, rng.random(n)),
        "i": rng.integers(-1, 500, (n, 5)).astype(np.int32),
        "u": rng.integers(0, 2, (n, 2, 3)).astype(np.uint8),
        "t": np.arange(n, dtype=np.int64) * 10**9,
        "s": np.array([f"ping-{i}-é" if i % 3 else "" for i in range(n)], dtype=object),
    }
    fills = {"f": np.nan, "d": np.nan, "i": -1, "u": 0, "t": 0, "s": ""}
    stores = {}
    for which in ("zarr", "direct"):
        root = zarr.open_group(str(tmp_path / f"{which}.zarr"), mode="w", zarr_format=3)
        for name, v in values.items():
            root.create_array(name, shape=v.shape, chunks=(k, *v.shape[1:]),
                              dtype=str if name == "s" else v.dtype, fill_value=fills[name],
                              **array_codec_kwargs())
        stores[which] = tmp_path / f"{which}.zarr"
    zroot = zarr.open_group(str(stores["zarr"]), mode="r+")
    writer = ChunkWriter.open(stores["direct"], list(values))
    assert writer is not None
    for c in range(3):  # chunks of 4, 4 and 2 (edge) rows
        sl = slice(c * k, min(n, (c + 1) * k))
        for name, v in values.items():
            zroot[name][sl] = v[sl]
        writer.write(c, {name: v[sl] for name, v in values.items()})
    for name in values:
        files = sorted(p.relative_to(stores["zarr"]) for p in (stores["zarr"] / name / "c").rglob("*") if p.is_file())
        assert len(files) == 3, name
        for f in files:
            assert (stores["direct"] / f).read_bytes() == (stores["zarr"] / f).read_bytes(), f
        back = zarr.open_group(str(stores["direct"]), mode="r")[name][:]
        if back.dtype.kind == "f":
            np.testing.assert_array_equal(back, values[name])
        else:
            assert back.tolist() == values[name].tolist(), name
    assert not any((stores["direct"] / ".sonarmap" / "tmp").iterdir())  # temporaries all moved
    # A writer never writes into a store that was replaced after it was made.
    os.replace(stores["direct"], tmp_path / "aside.zarr")
    stores["direct"].mkdir()
    with pytest.raises(StoreReplacedError):
        writer.write(0, {name: v[:k] for name, v in values.items()})
    assert not any(stores["direct"].iterdir())


def _kld_store(path: Path) -> Path:
    """A product-like store: one float64 variable of 24 pings in chunks of 8, this version's codecs."""
    import zarr

    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    arr = root.create_array("kld", shape=(24,), chunks=(8,), dtype=np.float64, fill_value=np.nan,
                            dimension_names=("ping_time",), **array_codec_kwargs())
    arr[...] = np.arange(24.0)
    return path


def test_chunk_rows_never_write_into_a_replaced_store(tmp_path: Path) -> None:
    """A worker's chunk writer checks the store directory's identity before every chunk: a store
    removed or re-created since the run started (``--overwrite`` while a killed run's worker is
    still busy) is left alone."""
    serial_store = _kld_store(tmp_path / "s.zarr")
    out = tmp_path / "c.zarr"
    shutil.copytree(serial_store, out)
    writer = ChunkRows.open(out)
    rows = {"kld": np.full(8, 0.5)}
    chunk = types.SimpleNamespace(index=1, start=8, stop=16)  # a ChunkRange, e.g. a survey's ChunkSpec
    writer.write(chunk, rows)
    import zarr

    np.testing.assert_array_equal(zarr.open_group(str(out), mode="r")["kld"][8:16], rows["kld"])
    os.replace(out, tmp_path / "aside.zarr")
    shutil.copytree(serial_store, out)
    before = sorted(p.read_bytes() for p in (out / "kld").rglob("*") if p.is_file())
    with pytest.raises(StoreReplacedError):
        writer.write(chunk, rows)
    assert sorted(p.read_bytes() for p in (out / "kld").rglob("*") if p.is_file()) == before


@pytest.mark.parametrize("fmt", [2, 3])
def test_chunk_keys_and_grid_are_the_files_zarr_writes(tmp_path: Path, fmt: int) -> None:
    """:func:`chunk_key` / :func:`chunk_grid` name exactly the chunk files zarr writes (v2 and v3
    keys, whole array and a range of rows), which is what the checks of missing chunks rely on."""
    import zarr

    from sonarmap.store.check import chunk_grid

    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w", zarr_format=fmt)
    kw = {"compressors": None} if fmt == 2 else array_codec_kwargs()
    arr = root.create_array("a", shape=(10, 5, 3), chunks=(4, 2, 3), dtype="int16", fill_value=-1, **kw)
    arr[...] = np.arange(150, dtype=np.int16).reshape(10, 5, 3)
    sep, v2 = (".", True) if fmt == 2 else ("/", False)
    written = {str(p.relative_to(tmp_path / "s.zarr" / "a")) for p in (tmp_path / "s.zarr" / "a").rglob("*")
               if p.is_file() and p.name not in (".zarray", ".zattrs", "zarr.json")}
    keys = {chunk_key(c, separator=sep, v2=v2) for c in chunk_grid(arr.shape, arr.chunks)}
    assert keys == written and len(keys) == 3 * 3
    assert {chunk_key(c, separator=sep, v2=v2) for c in chunk_grid(arr.shape, arr.chunks, slice(4, 5))} == {
        chunk_key((1, j, 0), separator=sep, v2=v2) for j in range(3)}
    assert list(chunk_grid((0, 3), (4, 3))) == [] and list(chunk_grid((), ())) == [()]
    assert chunk_key((), v2=True) == "0" and chunk_key((2, 0)) == "c/2/0"
