"""Survey plans: the pings of a survey cut into chunks, and the run's fingerprint (for resume)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._config import jsonable
from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.datamodel import SURVEY_FORMAT
from sonarmap.store import DEFAULT_CHUNK_SIZE
from sonarmap.ping import Ping

__all__ = ["DEFAULT_CHUNK_SIZE", "PingFunction", "SurveyExistsError", "ChunkSpec", "SurveyPlan", "plan_survey"]



PingFunction = Callable[..., Any]

class SurveyExistsError(SonarmapError, FileExistsError):
    """The output exists and is not a resumable run of the same command."""


# ============================================================================ planning
@dataclasses.dataclass(frozen=True)
class ChunkSpec:
    """One task: pings ``start:stop`` of the survey, read from ``items``.

    Parameters
    ----------
    index : int
        Chunk number; the chunk is stored in zarr chunk ``index`` of every product variable.
    start, stop : int
        Survey-wide ping positions.
    items : tuple of (path, format, first, count)
        Where the pings are: ``count`` consecutive pings of ``path`` starting at frame ``first``.
    geometry : SonarGeometry, preset name or JSON path, optional
        Geometry override handed to the readers.
    """

    index: int
    start: int
    stop: int
    items: tuple[tuple[str, str, int, int], ...]
    geometry: Any = None

    @property
    def n_pings(self) -> int:
        """Number of pings in the chunk."""
        return self.stop - self.start


@dataclasses.dataclass(frozen=True)
class SurveyPlan:
    """The pings of a survey, in order, and how they are chunked.

    ``files`` lists ``(path, format, n_pings)``; ``stamps`` the size and modification time of each
    file (part of the fingerprint, so changed inputs are not silently resumed).
    """

    files: tuple[tuple[str, str, int], ...]
    stamps: tuple[tuple[int, int], ...]
    chunk_size: int
    geometry: Any = None

    @property
    def n_pings(self) -> int:
        """Total number of pings."""
        return int(self._offsets[-1]) + self.files[-1][2] if self.files else 0

    @property
    def n_chunks(self) -> int:
        """Number of chunks (tasks)."""
        return max(1, math.ceil(self.n_pings / self.chunk_size)) if self.n_pings else 0

    def chunk(self, index: int) -> ChunkSpec:
        """The :class:`ChunkSpec` of chunk ``index``."""
        start = index * self.chunk_size
        stop = min(self.n_pings, start + self.chunk_size)
        if not 0 <= start < stop:
            raise InputError(f"chunk index {index} out of range 0-{self.n_chunks - 1}")
        offs = self._offsets
        i = int(np.searchsorted(offs, start, side="right")) - 1
        items: list[tuple[str, str, int, int]] = []
        while i < len(self.files) and offs[i] < stop:
            path, fmt, n = self.files[i]
            lo = max(start, int(offs[i])) - int(offs[i])
            hi = min(stop, int(offs[i]) + n) - int(offs[i])
            if hi > lo:
                items.append((path, fmt, lo, hi - lo))
            i += 1
        return ChunkSpec(index, start, stop, tuple(items), self.geometry)

    @property
    def _offsets(self) -> NDArray[np.int64]:
        """Survey position of each file's first ping (cached)."""
        cached = self.__dict__.get("_offsets_cache")
        if cached is None:
            counts = np.fromiter((n for _, _, n in self.files), dtype=np.int64, count=len(self.files))
            cached = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
            object.__setattr__(self, "_offsets_cache", cached)
        return cached

    def chunks(self) -> list[ChunkSpec]:
        """All chunks, in order."""
        return [self.chunk(i) for i in range(self.n_chunks)]


def plan_survey(
    inputs: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    geometry: Any = None,
) -> SurveyPlan:
    """List the pings of ``inputs`` (files, directories, globs) without decoding images.

    PNG/BMP pings given together are ordered by time stamp, as :func:`sonarmap.io.read_pings`
    does; multi-ping files contribute their frames in file order.

    Raises
    ------
    InputError
        If ``chunk_size`` is not a positive integer or the inputs hold no ping.
    DataFormatError
        If an input does not exist or is of an unknown format.
    """
    from sonarmap.io import expand_inputs, inputs_with_readers
    from sonarmap.io.pngjson import find_png_pings

    if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
        raise InputError(f"chunk_size: must be a positive integer (got {chunk_size!r})")
    files: list[tuple[str, str, int]] = []
    pngs: list[Path] = []

    def flush() -> None:
        if pngs:
            files.extend((os.path.abspath(p), "pngjson", 1) for p in find_png_pings(list(pngs)))
            pngs.clear()

    for p, reader in inputs_with_readers(expand_inputs(inputs)):
        if reader.FORMAT == "pngjson":
            pngs.append(p)
            continue
        flush()
        n = int(reader.count_pings(p))
        if n:
            files.append((os.path.abspath(p), reader.FORMAT, n))
    flush()
    if not files:
        raise InputError("inputs: no pings found")
    stamps = []
    for path, _, _ in files:
        st = os.stat(path)
        stamps.append((int(st.st_size), int(st.st_mtime_ns)))
    return SurveyPlan(tuple(files), tuple(stamps), int(chunk_size), geometry)


# ============================================================================ per-chunk work
def _iter_chunk_pings(chunk: ChunkSpec) -> Iterator[Ping]:
    """The pings of one chunk: for each ``(path, format, first, count)`` item, pings
    ``first:first+count`` of the file through its reader's ``start``/``stop`` (the pings before
    ``first`` are not decoded; a survey store reads only the chunks that hold them)."""
    from sonarmap.io import reader_for

    for path, fmt, first, count in chunk.items:
        got = 0
        for ping in reader_for(fmt).iter_pings(Path(path), geometry=chunk.geometry, start=first, stop=first + count):
            got += 1
            yield ping
        if got != count:
            raise DataFormatError(f"expected {count} pings from frame {first}, found {got}", path)


def _default_ping_function() -> PingFunction:
    from sonarmap.pipeline import process_ping

    return process_ping


# ============================================================================ configuration
def _resolve_config(config: Any) -> Any:
    from sonarmap.pipeline import PipelineConfig

    if config is None:
        return PipelineConfig()
    if isinstance(config, PipelineConfig):
        return config
    if isinstance(config, Mapping):
        return PipelineConfig.from_dict(dict(config))
    if isinstance(config, str | os.PathLike):
        return PipelineConfig.from_toml(config)
    raise InputError(f"config: expected PipelineConfig, mapping or TOML path, got {type(config).__name__}")


def _geometry_token(geometry: Any) -> Any:
    if geometry is None:
        return None
    from sonarmap.geometry import SonarGeometry

    if isinstance(geometry, SonarGeometry):
        return {"name": geometry.name, "key": geometry.key}
    p = Path(str(geometry))
    if p.exists():
        return {"file": os.path.abspath(p), "sha": hashlib.blake2b(p.read_bytes(), digest_size=16).hexdigest()}
    return {"preset": str(geometry)}


def _fingerprint(plan: SurveyPlan, config: dict[str, Any], *, keep_labels: bool, poses: Any,
                 extrinsics: Any, version: str, ping_function: str, background: dict[str, Any] | None = None) -> str:
    h = hashlib.blake2b(digest_size=20)
    head = {
        "format": SURVEY_FORMAT,
        "version": version,
        "config": jsonable(_options_by_name(config)),
        "keep_labels": bool(keep_labels),
        "chunk_size": plan.chunk_size,
        "geometry": _geometry_token(plan.geometry),
        "poses": None if poses is None else _file_token(poses),
        "extrinsics": None if extrinsics is None else _file_token(extrinsics),
        "ping_function": ping_function,
    }
    if background is not None:  # only then: the fingerprints of runs without a calibration stay as they were
        head["background"] = jsonable(background)
    h.update(json.dumps(head, sort_keys=True).encode())
    for (path, fmt, n), (size, mtime) in zip(plan.files, plan.stamps, strict=True):
        h.update(f"{path}\0{fmt}\0{n}\0{size}\0{mtime}\n".encode())
    return h.hexdigest()


def _options_by_name(config: dict[str, Any]) -> dict[str, Any]:
    """A pipeline configuration dict with its section tables merged into the top level: the
    options by name, as the fingerprint hashed them before the configuration had sections (so
    stores made then still resume).  Other dicts pass unchanged."""
    from sonarmap.config import SECTIONS

    out = {k: v for k, v in config.items() if not (k in SECTIONS and isinstance(v, dict))}
    for name in SECTIONS:
        if isinstance(config.get(name), dict):
            out.update(config[name])
    return out


def _file_token(path: Any) -> Any:
    p = Path(str(path))
    if not p.is_file():
        return repr(path)
    return {"file": os.path.abspath(p), "sha": hashlib.blake2b(p.read_bytes(), digest_size=16).hexdigest()}


def _function_name(fn: PingFunction | None) -> str:
    if fn is None:
        return "sonarmap.pipeline.process_ping"
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"


def _sub_chunk(chunk: ChunkSpec, lo: int, hi: int) -> ChunkSpec:
    """Pings ``lo:hi`` (positions within the chunk) of ``chunk`` as a :class:`ChunkSpec` of its own
    (same ``index``: a part is never stored on its own)."""
    if not 0 <= lo < hi <= chunk.n_pings:
        raise InputError(f"chunk {chunk.index}: part {lo}:{hi} out of range 0:{chunk.n_pings}")
    items: list[tuple[str, str, int, int]] = []
    pos = 0
    for path, fmt, first, count in chunk.items:
        a, b = max(lo, pos), min(hi, pos + count)
        if b > a:
            items.append((path, fmt, first + a - pos, b - a))
        pos += count
    return ChunkSpec(chunk.index, chunk.start + lo, chunk.start + hi, tuple(items), chunk.geometry)


#: Minimum pings per part when the tail is split (a part costs a task round trip: keep it useful).
_MIN_PART = 4

def _tail_parts(chunks: list[ChunkSpec], workers: int) -> list[tuple[ChunkSpec, ChunkSpec | None]]:
    """Jobs ``(chunk, part or None)``: the chunks in order, the last ``workers`` of them cut into
    ``2 * workers`` parts each.

    Whole chunks keep the workers busy with few round trips; near the end, when fewer chunks than
    workers remain, each worker would otherwise idle while another finishes a whole chunk (on
    average half a chunk of lost time per worker).  Parts bound that to half a part.
    """
    n_split = min(workers, len(chunks))
    jobs: list[tuple[ChunkSpec, ChunkSpec | None]] = [(c, None) for c in chunks[: len(chunks) - n_split]]
    for c in chunks[len(chunks) - n_split :]:
        n = max(1, min(2 * workers, c.n_pings // _MIN_PART))
        if n == 1:
            jobs.append((c, None))
            continue
        edges = [round(i * c.n_pings / n) for i in range(n + 1)]
        jobs.extend((c, _sub_chunk(c, lo, hi)) for lo, hi in zip(edges[:-1], edges[1:], strict=True))
    return jobs


def _maybe_config(config: Any) -> Any:
    """Configuration for an injected ping function: resolved if the pipeline module exists."""
    try:
        return _resolve_config(config)
    except ModuleNotFoundError:
        return config
