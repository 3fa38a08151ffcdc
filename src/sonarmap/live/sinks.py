"""Where a live run's products go: per-beam ranges as CSV / JSON lines, and a growing product store.

:class:`RangesSink` writes the rows of ``sonarmap ranges`` (same columns, same writer:
:func:`sonarmap.ranges.csv_rows.write_ranges_rows`) or one JSON object per ping, flushed after every
ping so a pipe downstream sees each ping at once.

:class:`BagSink` writes each ping's ranges as a ``marine_acoustic_msgs/SonarRanges`` message into
a ROS 1 or ROS 2 bag (:class:`sonarmap.io.rosbag_products.RangesBagWriter`), stamped with the
ping's time; the bag is written beside its path and moved there when the run ends (also on
Ctrl-C), so a replay tool never sees half a bag.

:class:`StoreSink` appends products to a zarr product store (the layout ``sonarmap process``
writes; :class:`sonarmap.survey.ProductAppender`): rows are buffered and flushed every
``flush_every`` pings or ``flush_s`` seconds, whichever comes first; each flush is published
atomically for readers, so :func:`sonarmap.survey.open_products` or ``xarray.open_zarr`` on the
store while it is written give a consistent prefix of the pings.
"""

from __future__ import annotations

import csv
import json
import math
import os
import queue
import threading
import time
from pathlib import Path
from typing import IO, Any

import numpy as np

from sonarmap.errors import InputError
from sonarmap.ping import Ping

__all__ = ["RangesSink", "StoreSink", "BagSink", "RANGES_FORMATS"]

#: Formats of :class:`RangesSink`.
RANGES_FORMATS = ("csv", "jsonl")


def _num(v: float) -> float | None:
    return None if not math.isfinite(v) else v


class RangesSink:
    """Per-beam ranges of every processed ping on a text stream, flushed per ping.

    Parameters
    ----------
    stream : text file
        Where to write (e.g. ``sys.stdout``).
    format : str
        ``"csv"`` (the ``sonarmap ranges`` columns, header first) or ``"jsonl"`` (one object per
        ping: ``ping``, ``time``, ``time_ns``, ``flags`` and per-beam lists ``azimuth_rad``,
        ``bin``, ``range_m``, ``intensity``, ``sigma_m``, ``p_detect``; ``null`` where the beam
        has no return / no estimate).
    """

    def __init__(self, stream: IO[str], format: str = "csv") -> None:
        if format not in RANGES_FORMATS:
            raise InputError(f"format: {format!r} is not one of {', '.join(RANGES_FORMATS)}")
        self.stream = stream
        self.format = format
        self._csv = csv.writer(stream) if format == "csv" else None
        self.n_rows = 0
        self._header = False

    def write(self, ping: Ping, products: Any) -> None:
        """Write the rows of one ping and flush."""
        flags = ";".join(products.gates)
        if self._csv is not None:
            from sonarmap.ranges.csv_rows import CSV_HEADER, write_ranges_rows

            if not self._header:
                self._csv.writerow(CSV_HEADER)
                self._header = True
            self.n_rows += write_ranges_rows(self._csv, ping.source, products.ranges, flags, time_ns=ping.time_ns)
        else:
            self.stream.write(json.dumps(self.jsonl_row(ping, products, flags), allow_nan=False) + "\n")
            self.n_rows += 1
        self.stream.flush()

    @staticmethod
    def jsonl_row(ping: Ping, products: Any, flags: str) -> dict[str, Any]:
        """The JSON object of one ping (``null`` for "none" / "unknown")."""
        from sonarmap.ranges.csv_rows import iso_time

        r = products.ranges
        hit = [int(b) >= 0 for b in r.bin]
        sigma = getattr(r, "sigma_m", None)
        p_det = getattr(r, "p_detect", None)
        return {
            "ping": ping.source,
            "time": iso_time(ping.time_ns),
            "time_ns": int(ping.time_ns),
            "flags": flags,
            "azimuth_rad": [float(a) for a in r.azimuth_rad],
            "bin": [int(b) if h else None for b, h in zip(r.bin, hit, strict=True)],
            "range_m": [_num(float(v)) if h else None for v, h in zip(r.range_m, hit, strict=True)],
            "intensity": [_num(float(v)) if h else None for v, h in zip(r.intensity, hit, strict=True)],
            "sigma_m": [None if sigma is None or not h else _num(float(v))
                        for v, h in zip(sigma if sigma is not None else hit, hit, strict=True)],
            "p_detect": [None if p_det is None else _num(float(v))
                         for v in (p_det if p_det is not None else hit)],
        }

    def close(self) -> None:
        """Flush the stream (it is not closed: it may be stdout)."""
        try:
            self.stream.flush()
        except (OSError, ValueError):
            pass


class BagSink:
    """Each processed ping's ranges as a ``SonarRanges`` message in a bag, finished on :meth:`close`.

    Parameters
    ----------
    path : path-like
        ``*.bag``: a ROS 1 bag file; anything else: a ROS 2 bag directory.
    overwrite : bool
        Replace an existing bag (else an existing path is an error before any ping).
    topic, frame_id : str
        Topic and ``header.frame_id`` of the messages.
    """

    def __init__(self, path: str | os.PathLike[str], *, overwrite: bool = False, topic: str = "/sonar/ranges",
                 frame_id: str = "sonar") -> None:
        from sonarmap.io.rosbag_products import RangesBagWriter

        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise InputError(f"{self.path}: exists; pass --overwrite to replace it")
        self.version = 1 if self.path.suffix.lower() == ".bag" else 2
        self._out = RangesBagWriter(self.path, version=self.version, topic=topic, frame_id=frame_id)

    @property
    def n_written(self) -> int:
        """Messages written so far."""
        return self._out.n_written

    def write(self, ping: Ping, products: Any) -> None:
        """Append the ping's ranges."""
        self._out.write(ping.geometry, products.ranges)

    def close(self) -> None:
        """Finish the bag and move it onto its path (an empty run writes an empty bag)."""
        self._out.close()


def _warm_zarr() -> None:
    """Import the store's modules and start zarr's I/O event loop (an in-memory group) now, not
    while the first pings stream in: cold, that doubles the store's creation (~0.25 s)."""
    import zarr

    import sonarmap.survey  # noqa: F401 - the store's writers

    zarr.open_group(zarr.storage.MemoryStore(), mode="w", zarr_format=3)


class StoreSink:
    """Append products to a zarr product store as pings arrive.

    The store is created with the first ping (its schema and coordinates come from it); it must
    not exist unless ``overwrite``.  While the sink is open, the store's root attribute
    ``live_status`` is ``"writing"``; :meth:`close` flushes the rest and marks it complete.

    Parameters
    ----------
    path : path-like
        The store (``*.zarr``).
    config : PipelineConfig
        Recorded in the store's attributes.
    flush_every : int
        Flush after this many pings ...
    flush_s : float
        ... or when the oldest buffered ping is this old, whichever comes first.
    chunk_size : int
        Pings per zarr chunk (the batch default, 256).
    overwrite : bool
        Replace an existing output.
    inputs : sequence of str
        The source, for the ``inputs`` attribute.

    Raises
    ------
    InputError
        On invalid arguments.
    SurveyExistsError
        If the store exists and ``overwrite`` is false (checked when the sink is made).
    """

    def __init__(self, path: str | os.PathLike[str], *, config: Any, flush_every: int = 16, flush_s: float = 1.0,
                 chunk_size: int = 256, overwrite: bool = False, inputs: tuple[str, ...] = ()) -> None:
        from sonarmap._atomic import WriterLock
        from sonarmap.survey import SurveyExistsError

        if isinstance(flush_every, bool) or not isinstance(flush_every, int) or flush_every < 1:
            raise InputError(f"flush_every: must be a positive integer, got {flush_every!r}")
        if not (isinstance(flush_s, int | float) and math.isfinite(flush_s) and flush_s > 0):
            raise InputError(f"flush_s: must be a positive number of seconds, got {flush_s!r}")
        self.path = Path(path)
        if config is None:
            from sonarmap.pipeline import PipelineConfig

            config = PipelineConfig()
        self.config = config
        self.flush_every = flush_every
        self.flush_s = float(flush_s)
        self.chunk_size = chunk_size
        self.inputs = tuple(inputs)
        self._lock = WriterLock(self.path)
        self._lock.acquire()
        try:
            if self.path.exists() or self.path.is_symlink():
                if not overwrite:
                    raise SurveyExistsError(f"{self.path}: output exists; use --overwrite to replace it")
                from sonarmap.survey import remove_store

                remove_store(self.path)
        except BaseException:
            self._lock.release()
            raise
        self._appender: Any = None
        self._reference: tuple[Any, Any] = (None, None)
        _warm_zarr()
        #: Pings not stored because their sonar geometry differs from the first ping's.
        self.n_skipped = 0
        self._buffer: list[dict[str, Any]] = []
        self._oldest = 0.0
        self.n_flushes = 0
        self.flush_ms: list[float] = []
        # Flushes run in a writer thread: the processing loop never waits for the disk.
        self._jobs: queue.Queue[list[dict[str, Any]] | None] = queue.Queue()
        self._error: list[BaseException] = []
        self._writer: threading.Thread | None = None

    @property
    def n_written(self) -> int:
        """Pings published to the store so far."""
        return 0 if self._appender is None else int(self._appender.n_pings)

    def write(self, ping: Ping, products: Any) -> None:
        """Buffer one ping's products; flush when due.

        The first ping's products only start the store: the writer thread creates it (its schema
        and coordinates come from that ping; ~0.25 s of zarr metadata, which in the processing
        thread would hold up ~10 pings of a 40 Hz sonar) and then appends what was flushed
        meanwhile.  An error creating it is raised by the next call.
        """
        from sonarmap.survey import product_record

        self._raise_error()
        if self._writer is None:
            self._reference = (np.asarray(ping.geometry.azimuth_rad), np.asarray(ping.geometry.range_m))
            self._writer = threading.Thread(target=self._write_loop, args=(ping, products),
                                            name="sonarmap-live-store", daemon=True)
            self._writer.start()
        elif not (np.array_equal(ping.geometry.azimuth_rad, self._reference[0])
                  and np.array_equal(ping.geometry.range_m, self._reference[1])):
            # One store holds one sonar configuration (as sonarmap process): keep the run going.
            self.n_skipped += 1
            if self.n_skipped == 1:
                import warnings

                from sonarmap.live.sources import LiveWarning

                warnings.warn(f"{ping.source}: the sonar geometry (beams / range window) changed; pings of "
                              f"another geometry than the first are not stored in {self.path}", LiveWarning,
                              stacklevel=2)
            return
        if not self._buffer:
            self._oldest = time.monotonic()
        self._buffer.append(product_record(products))
        if self.due():
            self.flush()

    def due(self) -> bool:
        """Whether buffered rows should be flushed now."""
        return bool(self._buffer) and (len(self._buffer) >= self.flush_every
                                       or time.monotonic() - self._oldest >= self.flush_s)

    def tick(self) -> None:
        """Flush if the oldest buffered ping is ``flush_s`` old (called while the loop is idle)."""
        if self.due():
            self.flush()

    def flush(self) -> None:
        """Hand the buffered rows to the writer thread (published as one atomic step for readers)."""
        self._raise_error()
        if not self._buffer or self._writer is None:
            return
        rows, self._buffer = self._buffer, []
        self._jobs.put(rows)

    def _create(self, ping: Ping, products: Any) -> None:
        """Create the store from the first ping (writer thread)."""
        import uuid

        from sonarmap.survey import ProductAppender, create_product_store

        create_product_store(self.path, ping, products, config=self.config, chunk_size=self.chunk_size,
                             inputs=self.inputs, fingerprint=f"live-{uuid.uuid4().hex}")
        self._appender = ProductAppender(self.path, range_m=ping.geometry.range_m)

    def _write_loop(self, ping: Ping, products: Any) -> None:
        try:
            self._create(ping, products)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            self._error.append(exc)
        while True:
            rows = self._jobs.get()
            if rows is None:
                return
            end = False
            while not self._jobs.empty():  # behind: publish everything waiting in one flush
                more = self._jobs.get()
                if more is None:
                    end = True
                    break
                rows = rows + more
            if self._error:  # a failed flush or creation: nothing more is written
                if end:
                    return
                continue
            t0 = time.perf_counter()
            try:
                self._appender.append(rows)
            except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
                self._error.append(exc)
                if end:
                    return
                continue
            self.n_flushes += 1
            self.flush_ms.append(1e3 * (time.perf_counter() - t0))
            if end:
                return

    def _raise_error(self) -> None:
        if self._error:
            raise self._error[0]

    def close(self) -> None:
        """Flush what is buffered, wait for the writer, mark the store complete, release the lock.

        Raises
        ------
        DataFormatError
            If a flush failed (e.g. the disk is full); the store then holds the pings of the
            flushes before.
        """
        try:
            if self._writer is not None:
                if self._buffer:
                    rows, self._buffer = self._buffer, []
                    self._jobs.put(rows)
                self._jobs.put(None)
                self._writer.join()
                self._raise_error()
                if self._appender is not None:
                    self._appender.close()
        finally:
            self._lock.release()
