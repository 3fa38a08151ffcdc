"""Writing the raw-ping store: :class:`SurveyWriter`, :func:`write_survey` and extra variables.

A store holds pings of one image shape ``(n_bins, n_beams)``.  :class:`SurveyWriter` writes in
chunks of ``chunk_pings`` (bounded memory); a new store is written to a temporary directory and
moved into place on success (atomic).  Appending to an existing store (``mode="a"``) is done in
place; an interrupted append leaves arrays of unequal length, which
:func:`sonarmap.store.open_survey` detects (and repairs with ``repair=True``).  Per-ping products
of later processing stages (e.g. ranges with dims ``(ping_time, beam)``) are declared with
:class:`~sonarmap.store.PingVariable` and either written with each ping
(``SurveyWriter(extra_variables=...)``) or added to an existing store with
:func:`add_ping_variable` + :func:`write_ping_variable` (region writes, resumable).

Every chunk is written with a CRC32C checksum (:func:`sonarmap.store.chunks.checksum_codecs`) and
every chunk is written, even one equal to the fill value.  Every store has consolidated metadata,
written when a writer is done and removed while one changes the store
(:func:`sonarmap.store.metadata.consolidate`).  A writer holds an exclusive lock on its store
(:class:`sonarmap._atomic.WriterLock`): a second writer fails at once, naming the first's pid.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from sonarmap._atomic import WriterLock, remove_stale_dirs, replace_output, temp_dir_beside, write_error
from sonarmap.datamodel import (
    COORD_AZIMUTH,
    DIM_BEAM,
    DIM_PING,
    DIM_RANGE,
    META_PREFIX,
    PING_TIME_UNITS,
    VAR_INTENSITY,
)
from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.ping import Ping
from sonarmap.store.check import _dims, inspect_store, is_zarr_store
from sonarmap.store.chunks import checksum_codecs, create_array
from sonarmap.store.metadata import consolidate, invalidate_consolidated
from sonarmap.store.pings import (
    PingVariable,
    _State,
    _check_ping_for_store,
    _extra_shape,
    _global_attrs,
    _ping_lengths,
    _read_state,
    inspect_survey,
    pings_to_dataset,
    survey_length,
)

if TYPE_CHECKING:  # pragma: no cover
    import xarray as xr

__all__ = [
    "SurveyWriter",
    "add_ping_variable",
    "write_ping_variable",
    "write_survey",
]

def _encoding(ds: xr.Dataset, chunk_pings: int) -> dict[str, dict[str, Any]]:
    enc: dict[str, dict[str, Any]] = {
        DIM_PING: {"units": PING_TIME_UNITS, "dtype": "int64", "chunks": (max(chunk_pings, 1024),),
                   **checksum_codecs()},
        DIM_RANGE: checksum_codecs(),
        DIM_BEAM: checksum_codecs(),
    }
    for name, var in ds.variables.items():
        if name in (DIM_PING, DIM_RANGE, DIM_BEAM):
            continue
        e: dict[str, Any] = dict(checksum_codecs())
        if var.dims and var.dims[0] == DIM_PING:
            e["chunks"] = (chunk_pings, *var.shape[1:])
            if var.dtype.kind in "iub" and name.startswith(META_PREFIX):
                e["fill_value"] = None
        enc[str(name)] = e
    return enc


class SurveyWriter:
    """Write pings to a zarr survey store in chunks along ``ping_time``.

    Parameters
    ----------
    path : path-like
        The store (a directory, conventionally ``*.zarr``).
    mode : {"w", "a"}
        ``"w"``: create (replacing an existing store) atomically on :meth:`close`;
        ``"a"``: append to an existing store in place (created if missing).
    chunk_pings : int
        Pings per chunk (and per write); memory holds at most one chunk.
    extra_variables : sequence of PingVariable
        Extra per-ping variables given to :meth:`add`.

    Use as a context manager; on an exception a new store is discarded (an existing one is left
    untouched in ``"w"`` mode).  The writer holds an exclusive lock on the store
    (:class:`sonarmap._atomic.WriterLock`) from construction to :meth:`close` / :meth:`abort`;
    temporary directories of earlier writers that were killed are removed when it is taken.
    Every chunk is written with a CRC32C checksum (:func:`checksum_codecs`).

    Raises
    ------
    DataFormatError
        If another writer holds the store, or it cannot be written (the message names it).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        mode: str = "w",
        chunk_pings: int = 16,
        extra_variables: Sequence[PingVariable] = (),
    ) -> None:
        if mode not in ("w", "a"):
            raise InputError(f"mode must be 'w' or 'a', got {mode!r}")
        if int(chunk_pings) < 1:
            raise InputError(f"chunk_pings must be >= 1, got {chunk_pings}")
        self.path = Path(path)
        self.chunk_pings = int(chunk_pings)
        self.extra_variables = tuple(extra_variables)
        self._buffer: list[Ping] = []
        self._extras: dict[str, list[Any]] = {v.name: [] for v in self.extra_variables}
        self._state = _State()
        self._written = 0
        self._closed = False
        self._tmp: Path | None = None
        self._invalidated = False
        self._lock = WriterLock(self.path).acquire()
        try:
            remove_stale_dirs(self.path)
            self._append = mode == "a" and is_zarr_store(self.path)
            if self._append:
                self._target = self.path
                self._state = _read_state(self.path)
                self._written = survey_length(self.path)
            else:
                try:
                    self._tmp = temp_dir_beside(self.path)
                except OSError as exc:
                    raise write_error(exc, self.path, "cannot create the store") from None
                self._target = self._tmp / "store.zarr"
        except BaseException:
            self._lock.release()
            raise

    @property
    def n_written(self) -> int:
        """Pings written to the store so far (excluding the buffer)."""
        return self._written

    def add(self, ping: Ping, **extras: Any) -> None:
        """Buffer one ping (and its extra-variable values); writes a chunk when the buffer is full.

        Raises
        ------
        InputError
            If the writer is closed, an extra variable is undeclared, or the ping cannot be stored
            (time outside 1970-2262, intensities outside [0, 1]).
        """
        if self._closed:
            raise InputError("SurveyWriter is closed")
        unknown = set(extras) - set(self._extras)
        if unknown:
            raise InputError(f"undeclared extra variables: {', '.join(sorted(unknown))}")
        _check_ping_for_store(ping)
        self._buffer.append(ping)
        for name, values in self._extras.items():
            var = next(v for v in self.extra_variables if v.name == name)
            values.append(extras.get(name, np.full(_extra_shape(var, ping.shape), var.fill_value)))
        if len(self._buffer) >= self.chunk_pings:
            self.flush()

    def write(self, pings: Iterable[Ping], progress: Callable[[int], None] | None = None) -> int:
        """Add every ping of ``pings``; ``progress(n)`` is called after each one. Returns the count."""
        n = 0
        for p in pings:
            self.add(p)
            n += 1
            if progress is not None:
                progress(1)
        return n

    def flush(self) -> None:
        """Write the buffered pings as one chunk.

        Raises
        ------
        DataFormatError
            If the store cannot be written (disk full ...); the message names the store.
        """
        if not self._buffer:
            return
        declared = {v.name for v in self.extra_variables}
        stored = [v for name, v in self._state.extras.items() if name not in declared]
        per_ping_before = self._state.azimuth_per_ping
        ds = pings_to_dataset(
            self._buffer,
            extras=self._extras,
            extra_variables=(*self.extra_variables, *stored),  # undeclared: fill values
            _state=self._state,
        )
        try:
            if self._written == 0 and not self._append:
                ds.to_zarr(self._target, mode="w", encoding=_encoding(ds, self.chunk_pings), consolidated=False,
                           write_empty_chunks=True)
            else:
                if self._append and not self._invalidated:
                    # First change of an existing store: until close() re-consolidates, readers
                    # that trust consolidated metadata fall back to the arrays' own.
                    invalidate_consolidated(self._target)
                    self._invalidated = True
                if self._state.azimuth_per_ping and not per_ping_before:
                    _azimuth_per_ping(self._target, self._written, self.chunk_pings)
                _check_append_compatible(self._target, ds)
                ds.to_zarr(self._target, append_dim=DIM_PING, consolidated=False, write_empty_chunks=True)
                _update_attrs(self._target, _global_attrs(self._state))
        except SonarmapError:
            raise
        except OSError as exc:
            raise write_error(exc, self.path, "cannot write the store") from None
        self._written += len(self._buffer)
        self._buffer.clear()
        for v in self._extras.values():
            v.clear()

    def close(self) -> None:
        """Flush and, for a new store, move it into place atomically; releases the store's lock."""
        if self._closed:
            return
        try:
            self.flush()
            self._closed = True
            if self._tmp is None:
                if self._written:
                    consolidate(self._target)
                return
            if self._written == 0:
                shutil.rmtree(self._tmp, ignore_errors=True)
                raise InputError(f"{self.path}: no pings to write")
            consolidate(self._target)
            try:
                replace_output(self._target, self.path)
            except OSError as exc:
                raise write_error(exc, self.path, "cannot move the new store into place") from None
            shutil.rmtree(self._tmp, ignore_errors=True)
        finally:
            if self._closed:
                self._lock.release()

    def abort(self) -> None:
        """Discard a new store (no effect on appends already written); releases the store's lock."""
        self._closed = True
        try:
            if self._tmp is not None:
                shutil.rmtree(self._tmp, ignore_errors=True)
            elif self._append and self._invalidated:
                _consolidate_if_whole(self._target)
        finally:
            self._lock.release()

    def __enter__(self) -> SurveyWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            try:
                self.close()
            except BaseException:
                self.abort()
                raise
        else:
            self.abort()


def _update_attrs(path: Path, attrs: Mapping[str, Any]) -> None:
    import zarr

    zarr.open_group(str(path), mode="r+", use_consolidated=False).attrs.update(dict(attrs))


def _consolidate_if_whole(path: Path) -> None:
    """Consolidate the metadata of a store whose arrays along ``ping_time`` agree in length.

    An interrupted append (arrays of different lengths) is left without consolidated metadata:
    :func:`open_survey` reports (and repairs) it from the arrays' own metadata.
    """
    try:
        lengths = _ping_lengths(inspect_survey(path))
    except DataFormatError:
        return
    if len(set(lengths.values())) <= 1:
        consolidate(path)


def _azimuth_per_ping(path: Path, n: int, chunk_pings: int) -> None:
    """Turn a store's ``beam_azimuth (beam)`` into ``(ping_time, beam)`` for its ``n`` pings.

    Called when a ping with another azimuth table than the store's is written: the pings already
    stored all have the store's table, so each of their rows is that table.
    """
    import zarr

    g = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    old = g[COORD_AZIMUTH]
    if _dims(old) != (DIM_BEAM,):
        return
    table = np.asarray(old[...], dtype=np.float64)
    attrs = dict(old.attrs)
    del g[COORD_AZIMUTH]
    create_array(g, COORD_AZIMUTH, np.broadcast_to(table, (n, table.size)) if n else None, shape=(n, table.size),
                 chunks=(chunk_pings, table.size), dtype=np.float64, fill_value=np.nan,
                 dimension_names=(DIM_PING, DIM_BEAM), attributes=attrs)


def _check_append_compatible(path: Path, ds: xr.Dataset) -> None:
    st = inspect_store(path)
    if VAR_INTENSITY in st.arrays:
        have = tuple(st.arrays[VAR_INTENSITY].shape[1:])
        want = tuple(ds[VAR_INTENSITY].shape[1:])
        if have != want:
            raise InputError(
                f"{path}: store holds images of shape {have}, cannot append shape {want}"
            )
    missing = [v for v in st.arrays if v not in ds.variables and v not in (DIM_RANGE, DIM_BEAM)]
    if missing:
        raise InputError(f"{path}: appended pings lack variables {', '.join(sorted(missing))}")


def write_survey(
    pings: Iterable[Ping],
    path: str | os.PathLike[str],
    *,
    append: bool = False,
    chunk_pings: int = 16,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Write pings to a zarr survey store; returns the number written.

    A new store is written atomically (temporary directory + rename); ``append=True`` adds to an
    existing store in chunks.  Memory holds one chunk of ``chunk_pings`` pings.
    """
    with SurveyWriter(path, mode="a" if append else "w", chunk_pings=chunk_pings) as w:
        return w.write(pings, progress)


def add_ping_variable(path: str | os.PathLike[str], var: PingVariable, *, chunk_pings: int | None = None) -> None:
    """Add an (unwritten, fill-valued) per-ping variable to an existing survey store.

    Existing variables of the same name are left as they are (the call is idempotent, so a
    resumed batch run can call it again).
    """
    import dask.array as da
    import xarray as xr

    p = Path(path)
    st = inspect_survey(p)
    if var.name in st.arrays:
        return
    state = _read_state(p)
    assert state.shape is not None
    n = survey_length(p)
    shape = (n, *_extra_shape(var, state.shape))
    cp = chunk_pings or int(st.arrays[VAR_INTENSITY].chunks[0])
    data = da.full(shape, var.fill_value, dtype=var.dtype, chunks=(cp, *shape[1:]))
    ds = xr.Dataset({var.name: ((DIM_PING, *var.dims), data, var.attrs())}, attrs=dict(st.attrs))
    enc: dict[str, Any] = {var.name: {"chunks": (cp, *shape[1:]), **checksum_codecs()}}
    if np.dtype(var.dtype).kind in "iub":
        enc[var.name]["fill_value"] = None
    try:
        invalidate_consolidated(p)
        ds.to_zarr(p, mode="a", encoding=enc, consolidated=False, compute=True, write_empty_chunks=True)
    except OSError as exc:
        raise write_error(exc, p, f"cannot add variable {var.name}") from None
    consolidate(p)


def write_ping_variable(
    path: str | os.PathLike[str],
    name: str,
    values: ArrayLike,
    *,
    start: int,
) -> None:
    """Write ``values`` (shape ``(n, ...)``) into variable ``name`` for pings ``start .. start+n``.

    Region writes aligned to the ``ping_time`` chunks are safe to run concurrently from several
    processes (each chunk is written by one writer).
    """
    import xarray as xr

    p = Path(path)
    st = inspect_store(p)
    if name not in st.arrays:
        raise InputError(f"{p}: no variable {name!r}; declare it with add_ping_variable first")
    arr = st.arrays[name]
    vals = np.asarray(values, dtype=arr.dtype)
    if vals.shape[1:] != tuple(arr.shape[1:]):
        raise InputError(f"{name}: values of shape {vals.shape[1:]} per ping, store has {arr.shape[1:]}")
    if not (0 <= start and start + vals.shape[0] <= arr.shape[0]):
        raise InputError(f"{name}: pings {start}..{start + vals.shape[0]} outside 0..{arr.shape[0]}")
    ds = xr.Dataset({name: (st.dims(name), vals)}, attrs=dict(st.attrs))
    try:
        ds.to_zarr(p, region={DIM_PING: slice(start, start + vals.shape[0])}, consolidated=False,
                   write_empty_chunks=True)
    except OSError as exc:
        raise write_error(exc, p, f"cannot write variable {name}") from None
