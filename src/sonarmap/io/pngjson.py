"""PNG/BMP image + sidecar JSON pings (the format of the paper authors' DIDSON data).

A ping is ``<ts>_raw.png`` or ``<ts>.png`` (or ``.bmp``) next to ``<ts>.json`` holding the geometry
(see :mod:`sonarmap.geometry`).  ``<ts>`` is an integer time stamp since the Unix epoch whose unit is
inferred from its digit count (10: s, 13: ms, 16: µs, 19: ns).  Images are 8-bit (0-255 -> [0, 1])
or 16-bit (0-65535 -> [0, 1]) greyscale; palettised images are converted through their palette.

Inputs are untrusted: images and sidecars are opened only if they are regular files (a FIFO or a
device named like a ping is refused, see :mod:`sonarmap._files`), sidecars are read up to
``MAX_SIDECAR_BYTES`` and validated field by field, and an image's size is checked from its header
against :data:`MAX_IMAGE_PIXELS` and the geometry before any pixel is decoded.  Every failure is a
:class:`~sonarmap.errors.DataFormatError` (or a :class:`~sonarmap.errors.GeometryError` for a
geometry that does not fit the image) naming the file.
"""

from __future__ import annotations

import contextlib
import glob
import io
import json
import os
import re
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._atomic import atomic_path, atomic_write_text
from sonarmap.errors import DataFormatError, GeometryError
from sonarmap.geometry import SonarGeometry, as_geometry, geometry_from_sidecar_bytes
from sonarmap.io.reader import GeometrySpec
from sonarmap._files import MAX_SIDECAR_BYTES, open_regular, read_bytes_bounded, require_regular_file
from sonarmap.ping import Ping

__all__ = [
    "IMAGE_SUFFIXES",
    "read_png_ping",
    "write_png_ping",
    "find_png_pings",
    "iter_png_pings",
    "sidecar_json",
    "time_ns_from_stem",
    "read_image_file",
    "MAX_IMAGE_PIXELS",
]

IMAGE_SUFFIXES = (".png", ".bmp")
#: Stems ending like this are products written beside pings (simulator truth, label images), not
#: pings; directory and glob listings skip them (an explicitly named file is still read).
PRODUCT_STEM_SUFFIXES = ("_truth", "_labels", "_mask")
_STAMP = re.compile(r"^(\d{9,19})(?:_raw)?$")
_UNIT_BY_DIGITS = {10: 10**9, 13: 10**6, 16: 10**3, 19: 1}
#: Largest image accepted, in pixels (64 Mpixel; a DIDSON ping is 49 152), checked from the file
#: header before decoding - below PIL's own decompression-bomb threshold, so PIL never warns.
MAX_IMAGE_PIXELS = 64 * 1024 * 1024
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: The only PIL decoders used: a ``.png`` that is really a TIFF or JPEG is refused, not decoded.
_PIL_FORMATS = ("PNG", "BMP")
_BMP_INFO_HEADERS = (40, 52, 56, 64, 108, 124)


def time_ns_from_stem(stem: str) -> int | None:
    """Integer nanoseconds from a ``<ts>`` or ``<ts>_raw`` file stem, or ``None``."""
    m = _STAMP.match(stem)
    if not m:
        return None
    digits = m.group(1)
    scale = _UNIT_BY_DIGITS.get(len(digits))
    if scale is None:
        return None
    return int(digits) * scale


def _base_stem(path: Path) -> str:
    stem = path.stem
    return stem[:-4] if stem.endswith("_raw") else stem


def sidecar_json(image_path: str | os.PathLike[str]) -> Path:
    """Path of the JSON sidecar of an image (``<ts>_raw.png`` -> ``<ts>.json``)."""
    p = Path(image_path)
    return p.with_name(_base_stem(p) + ".json")


#: An 8-bit level ``k`` is ``float32(k) * float32(1 / 255)`` in [0, 1].
_U8_SCALE = np.float32(1.0 / 255.0)


def _header_size(head: bytes, path: Path) -> tuple[int, int] | None:
    """``(width, height)`` from the first bytes of a PNG or BMP, or ``None`` for other content.

    Raises
    ------
    DataFormatError
        If a PNG does not start with its IHDR chunk (the PNG specification requires it first).
    """
    if head.startswith(_PNG_SIGNATURE):
        if len(head) < 24 or head[12:16] != b"IHDR":
            raise DataFormatError("corrupt or truncated image (no IHDR chunk after the PNG signature)", path)
        width, height = struct.unpack(">II", head[16:24])
        return int(width), int(height)
    if head.startswith(b"BM") and len(head) >= 26:
        info = int.from_bytes(head[14:18], "little")
        if info == 12:  # OS/2 1.x BITMAPCOREHEADER
            width, height = struct.unpack("<HH", head[18:22])
            return int(width), int(height)
        if info in _BMP_INFO_HEADERS:
            width, height = struct.unpack("<ii", head[18:26])
            return int(width), abs(int(height))  # negative height: rows stored top-down
    return None  # PIL refuses it (unsupported BMP header, or neither PNG nor BMP)


def _check_size(size: tuple[int, int], path: Path, geometry: SonarGeometry | None) -> None:
    """Refuse an empty or oversized image, or one whose shape is not the geometry's."""
    width, height = size
    if width < 1 or height < 1:
        raise DataFormatError(f"image header gives an empty image ({width} x {height} pixels)", path)
    if width * height > MAX_IMAGE_PIXELS:
        raise DataFormatError(
            f"image header gives {width} x {height} = {width * height} pixels, "
            f"more than the {MAX_IMAGE_PIXELS} allowed",
            path,
        )
    if geometry is not None and (height, width) != geometry.shape:
        raise GeometryError(
            f"{path}: image shape {(height, width)} does not match geometry '{geometry.name}' "
            f"(n_bins, n_beams) = {geometry.shape}"
        )


def read_image_file(
    path: str | os.PathLike[str],
    data: bytes | None = None,
    *,
    geometry: SonarGeometry | None = None,
) -> NDArray[np.float32]:
    """Decode a greyscale PNG/BMP into float32 in [0, 1].

    The image size is read from the file header and checked against :data:`MAX_IMAGE_PIXELS`
    (and ``geometry``) before any pixel is decoded.  Truncated or corrupt pixel data is an error,
    never a partly zero image.

    Parameters
    ----------
    path : path-like
        The image file (read only if it is a regular file), or the name used in messages when
        ``data`` is given.
    data : bytes, optional
        The file's content, already read.
    geometry : SonarGeometry, optional
        When given, the image must have shape ``geometry.shape`` = ``(n_bins, n_beams)``.

    Returns
    -------
    ndarray, shape (height, width), float32
        Intensities in [0, 1].

    Raises
    ------
    DataFormatError
        If the file is missing, not a regular file, truncated, corrupt, too large, not a PNG/BMP,
        or a colour image.
    GeometryError
        If ``geometry`` is given and the header's size does not match it.
    """
    from PIL import Image, UnidentifiedImageError

    p = Path(path)
    size: tuple[int, int] | None = None
    try:
        with contextlib.ExitStack() as stack:
            fh = io.BytesIO(data) if data is not None else stack.enter_context(open_regular(p, "image"))
            size = _header_size(fh.read(32), p)
            fh.seek(0)
            if size is not None:
                _check_size(size, p, geometry)
            im = stack.enter_context(Image.open(fh, formats=_PIL_FORMATS))
            _check_size(im.size, p, geometry)  # the size PIL will decode
            mode = im.mode
            if mode == "P":
                pal = np.asarray(im.getpalette() or [], dtype=np.uint8).reshape(-1, 3)
                if pal.size and not np.array_equal(pal[:, 0], pal[:, 1]):
                    raise DataFormatError("palette is not greyscale", p)
                im = stack.enter_context(im.convert("L"))
                mode = "L"
            arr = np.asarray(im)
    except (DataFormatError, GeometryError):
        raise
    except UnidentifiedImageError:
        if size is not None:  # a PNG/BMP header PIL could not parse further
            raise DataFormatError("corrupt or truncated image (PNG/BMP headers unreadable)", p) from None
        raise DataFormatError("not a PNG/BMP image (unrecognised content)", p) from None
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise DataFormatError(f"image too large ({exc})", p) from None
    except (OSError, SyntaxError, ValueError, EOFError, struct.error) as exc:
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise DataFormatError(f"corrupt or truncated image ({msg})", p) from None
    if arr.ndim != 2:
        raise DataFormatError(f"expected a greyscale image, got mode {mode} shape {arr.shape}", p)
    if arr.dtype == np.uint8:
        # astype + in-place multiply (float32): 5x faster than a 256-entry table gather, same bits
        out = arr.astype(np.float32)
        out *= _U8_SCALE
        return out
    if arr.dtype in (np.uint16, np.int32) or mode.startswith("I"):
        return (arr.astype(np.float32) / np.float32(65535.0)).clip(0, 1)
    if arr.dtype == np.bool_:
        return arr.astype(np.float32)
    raise DataFormatError(f"unsupported image mode {mode}", p)


def read_png_ping(
    path: str | os.PathLike[str],
    *,
    geometry: SonarGeometry | str | os.PathLike[str] | None = None,
) -> Ping:
    """Read one ping from an image and its sidecar JSON.

    The sidecar is read (at most ``MAX_SIDECAR_BYTES``) and validated first, then the image's
    header is checked against it, and only then are the pixels decoded.

    Parameters
    ----------
    path : path-like
        The image (``.png``/``.bmp``) or the sidecar ``.json`` (the image is then found beside it).
    geometry : SonarGeometry, preset name or JSON path, optional
        Overrides the sidecar; required when the image has no sidecar.

    Returns
    -------
    Ping
        The ping, its image float32 in [0, 1] (times the sidecar's ``intensity_scale``, if any).

    Raises
    ------
    DataFormatError
        Missing, non-regular, oversized, truncated or corrupt image or JSON (JSON errors give line
        and column).
    GeometryError
        When a sidecar field is invalid, or the image shape disagrees with the geometry.
    """
    p = Path(path)
    if p.suffix.lower() == ".json":
        stem = p.stem
        for cand in (f"{stem}_raw.png", f"{stem}.png", f"{stem}_raw.bmp", f"{stem}.bmp"):
            if (p.parent / cand).exists():
                p = p.parent / cand
                break
        else:
            raise DataFormatError("no image (<ts>_raw.png, <ts>.png or .bmp) beside this JSON", p)
    require_regular_file(p, "image")
    scale = 1.0
    if geometry is None:
        side = sidecar_json(p)
        if not os.path.lexists(side):
            raise DataFormatError(
                f"no sidecar JSON ({side.name}); pass a geometry (a preset or geometry JSON file: "
                "geometry=, or --sonar PRESET|JSON on the command line)", p
            )
        data = read_bytes_bounded(side, MAX_SIDECAR_BYTES, "sidecar JSON")
        geom = geometry_from_sidecar_bytes(data, str(side))
        if b'"intensity_scale"' in data:
            scale = _intensity_scale(data, side)
    else:
        geom = as_geometry(geometry)
    image = read_image_file(p, geometry=geom)
    if image.shape != geom.shape:  # pragma: no cover - the header check above guarantees it
        raise GeometryError(
            f"{p}: image shape {image.shape} does not match geometry '{geom.name}' "
            f"(n_bins, n_beams) = {geom.shape}"
        )
    if scale != 1.0:
        image = image * np.float32(scale)
    time_ns = time_ns_from_stem(p.stem)
    if time_ns is None:
        time_ns = 0
    return Ping(image=image, geometry=geom, time_ns=time_ns, source=str(p))


def _intensity_scale(data: bytes, side: Path) -> float:
    """The sidecar's ``intensity_scale``: stored pixels are ``image / intensity_scale``.

    ``data`` has already been parsed successfully as a JSON object by the geometry reader.
    """
    d = json.loads(data)
    value = d.get("intensity_scale", 1.0) if isinstance(d, dict) else 1.0
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < 1e12:
        raise DataFormatError(f"intensity_scale must be a positive number, got {value!r:.40}", side)
    return float(value)


def _encode_png(image: NDArray[Any], bit_depth: int) -> bytes:
    from PIL import Image

    if bit_depth == 8:
        q = np.rint(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
        im = Image.fromarray(q, mode="L")
    elif bit_depth == 16:
        q = np.rint(np.clip(image, 0.0, 1.0) * 65535.0).astype(np.uint16)
        im = Image.fromarray(q)
    else:
        raise ValueError(f"bit_depth: must be 8 or 16, got {bit_depth}")
    buf = io.BytesIO()
    im.save(buf, format="PNG")
    return buf.getvalue()


def write_png_ping(
    ping: Ping,
    directory: str | os.PathLike[str],
    *,
    stem: str | None = None,
    raw_suffix: bool = True,
    bit_depth: int = 8,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``ping`` as ``<stem>_raw.png`` + ``<stem>.json``, atomically; returns the image path.

    ``stem`` defaults to the ping time in microseconds (the DIDSON data's naming).  8-bit output is
    lossless for 8-bit input; intensities outside [0, 1] are clipped (use ``bit_depth=16`` for finer
    quantisation).  ``extra`` entries are added to the JSON.
    """
    d = Path(directory)
    if stem is None:
        stem = str(ping.time_ns // 1000)
    img_path = d / (f"{stem}_raw.png" if raw_suffix else f"{stem}.png")
    data = _encode_png(ping.image, bit_depth)
    meta = ping.geometry.to_dict()
    if extra:
        meta.update(extra)
    with atomic_path(img_path) as tmp:
        tmp.write_bytes(data)
    atomic_write_text(d / f"{stem}.json", json.dumps(meta, indent=1) + "\n")
    return img_path


def _is_ping_image(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_SUFFIXES and not path.stem.endswith(PRODUCT_STEM_SUFFIXES)


def _sort_key(path: Path) -> tuple[int, int, str]:
    t = time_ns_from_stem(path.stem)
    return (0 if t is not None else 1, t or 0, str(path))


def find_png_pings(source: str | os.PathLike[str] | Iterable[str | os.PathLike[str]]) -> list[Path]:
    """Image files of pings in a directory, glob, file or list thereof, sorted by time stamp.

    Images without a parsable time stamp sort after stamped ones, by name.  JSON paths are mapped
    to their images.  Raises :class:`DataFormatError` when nothing matches.
    """
    items = [source] if isinstance(source, str | os.PathLike) else list(source)
    found: dict[str, Path] = {}
    for item in items:
        s = str(item)
        p = Path(s)
        if p.is_dir():
            cands = [c for c in p.iterdir() if _is_ping_image(c)]
        elif any(ch in s for ch in "*?["):
            cands = [Path(c) for c in glob.glob(s) if _is_ping_image(Path(c))]
        else:
            if not p.exists():
                raise DataFormatError("no such file or directory", p)
            cands = [p]
        for c in cands:
            found[str(c)] = c
    if not found:
        raise DataFormatError("no PNG/BMP pings found", ", ".join(str(i) for i in items))
    return sorted(found.values(), key=_sort_key)


def iter_png_pings(
    source: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    *,
    geometry: SonarGeometry | str | os.PathLike[str] | None = None,
    start: int = 0,
    stop: int | None = None,
) -> Iterator[Ping]:
    """Lazily yield pings ``start:stop`` in time-stamp order (one image in memory at a time; the
    file list is sorted first and only the files in range are read)."""
    from sonarmap.io.reader import check_ping_range

    start, stop = check_ping_range(start, stop)
    for p in find_png_pings(source)[start:stop]:
        yield read_png_ping(p, geometry=geometry)


# ---------------------------------------------------------------------- format-registry hooks
FORMAT = "pngjson"


def sniff(path: Path, head: bytes) -> bool:
    """PNG/BMP images, their JSON sidecars, or directories holding them."""
    if path.is_dir():
        return any(_is_ping_image(c) for c in path.iterdir())
    if head.startswith(b"\x89PNG\r\n\x1a\n") or head.startswith(b"BM"):
        return True
    if path.suffix.lower() == ".json":
        return any(
            (path.parent / f"{path.stem}{s}").exists()
            for s in ("_raw.png", ".png", "_raw.bmp", ".bmp")
        )
    return False


def iter_pings(path: str | os.PathLike[str], *, geometry: GeometrySpec = None, start: int = 0,
               stop: int | None = None, **_: Any) -> Iterator[Ping]:
    """Pings ``start:stop`` of a PNG/BMP file, directory or glob (the reader protocol):
    :func:`iter_png_pings`."""
    yield from iter_png_pings(path, geometry=geometry, start=start, stop=stop)


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of image files of a file, directory or glob (no decoding)."""
    return len(find_png_pings(path))
