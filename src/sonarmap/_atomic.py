"""Atomic file output and exclusive writers.

* :func:`atomic_path` / :func:`atomic_open`: write to a temporary file beside the target, then
  ``os.replace``.  Temporary files are named ``.{target name}.{pid}-{host}.{random}.tmp{suffix}``;
  those a killed run left behind (their process is gone) are removed by the next run writing the
  same target.  A write that fails (disk full, quota, read-only file system ...) is a
  :class:`~sonarmap.errors.DataFormatError` naming the target, which is left untouched.
* :func:`temp_dir_beside` / :func:`replace_output` / :func:`remove_output`: outputs that are
  directories (zarr stores, ROS 2 bags) or written by other libraries (ROS 1 bags) are built in a
  temporary directory ``.{name}.{random}.tmp`` beside the target and moved onto it with renames
  only; an output being replaced or removed is first renamed aside into ``.{name}.{random}.old``,
  so it is never half-deleted in place.  What killed writers left
  beside a target is removed by the next writer holding its lock (:func:`remove_stale_dirs`).
* :class:`WriterLock`: an exclusive claim on an output (a file or a store directory) for the life
  of one writer, so two writers never share a store.  The claim is ``flock`` on a lock file
  ``.{name}.lock`` beside the output, holding the writer's pid and host; the kernel drops it when
  the process ends however it ends, so the lock of a killed writer is simply taken over.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from sonarmap.errors import DataFormatError, SonarmapError

__all__ = [
    "atomic_path",
    "make_output_dir",
    "atomic_open",
    "atomic_write_bytes",
    "atomic_write_text",
    "remove_stale_temporaries",
    "temp_dir_beside",
    "replace_output",
    "remove_output",
    "remove_stale_dirs",
    "pid_alive",
    "write_error",
    "WriterLock",
    "STALE_TEMP_AGE_S",
]

#: Temporary files whose creator cannot be identified (another host, or the pre-pid naming) are
#: removed once they are this old.
STALE_TEMP_AGE_S = 3600.0

#: ``errno`` values that mean "the data could not be written" (not "an input is missing").
_WRITE_ERRNOS = frozenset(
    e for e in (errno.ENOSPC, getattr(errno, "EDQUOT", None), errno.EFBIG, errno.EROFS, errno.EIO)
    if e is not None
)

#: ``tempfile.mkstemp``'s random part: 8 characters of this alphabet.
_RANDOM = r"[a-z0-9_]{8}"


def _umask() -> int:
    """The process umask (read without changing it for longer than one call)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _host_tag() -> str:
    """A short, file-name-safe tag of this host (6 hex digits of a hash of its name)."""
    return hashlib.blake2b(socket.gethostname().encode("utf-8", "replace"), digest_size=3).hexdigest()


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (``True`` when that cannot be told)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: it exists, under another user
        return True
    return True


def write_error(exc: OSError, target: str | os.PathLike[str], what: str = "cannot write") -> DataFormatError:
    """A one-line :class:`DataFormatError` naming ``target`` for an ``OSError`` raised writing it."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    return DataFormatError(f"{what}: {reason}", target)


def make_output_dir(path: str | os.PathLike[str]) -> Path:
    """Create the output directory ``path`` (and its parents) unless it exists; returns it.

    Raises
    ------
    DataFormatError
        Naming the path in the way that is a file (``exists and is not a directory``), or
        ``path`` with the reason it cannot be created.

    Examples
    --------
    >>> import tempfile
    >>> make_output_dir(Path(tempfile.mkdtemp()) / "a" / "b").is_dir()
    True
    """
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocker = next((q for q in (p, *p.parents) if q.exists() and not q.is_dir()), p)
        raise DataFormatError("exists and is not a directory; give a directory", blocker) from None
    except OSError as exc:
        raise write_error(exc, p, "cannot create the output directory") from None
    return p


def _is_write_failure(exc: BaseException) -> bool:
    """An ``OSError`` (not one of ours) that means the data could not be written."""
    return isinstance(exc, OSError) and not isinstance(exc, SonarmapError) and exc.errno in _WRITE_ERRNOS


def remove_stale_temporaries(
    target: str | os.PathLike[str], suffix: str, *, max_age_s: float = STALE_TEMP_AGE_S
) -> list[Path]:
    """Remove the temporary files of :func:`atomic_path` for ``target`` that a dead run left.

    A temporary file is removed when the process that created it (pid in its name, this host) no
    longer exists, or - if its creator cannot be told (another host, or a name without a pid) -
    when it is older than ``max_age_s``.  Files of live processes (including this one) are kept.

    Returns
    -------
    list of Path
        The files removed.
    """
    t = Path(target)
    head, tail = f".{t.name}.", f".tmp{suffix}"
    pattern = re.compile(rf"(?:(\d+)-([0-9a-f]{{6}})\.)?{_RANDOM}")
    try:
        names = os.listdir(t.parent)
    except OSError:
        return []
    here, me = _host_tag(), os.getpid()
    removed = []
    now = time.time()
    for name in names:
        if not (name.startswith(head) and name.endswith(tail)) or len(name) <= len(head) + len(tail):
            continue
        m = pattern.fullmatch(name[len(head) : -len(tail)])
        if m is None:
            continue
        path = t.parent / name
        try:
            st = os.lstat(path)
        except OSError:
            continue
        if m.group(1) is not None and m.group(2) == here:
            pid = int(m.group(1))
            stale = pid != me and not pid_alive(pid)
        else:
            stale = now - st.st_mtime > max_age_s
        if stale:
            with contextlib.suppress(OSError):
                os.unlink(path)
                removed.append(path)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, suffix: str | None = None, clean: bool = True) -> Iterator[Path]:
    """Yield a temporary path in the target's directory; move it onto ``path`` on success.

    On any exception the temporary file is removed and ``path`` is left untouched, so a crash never
    leaves a half-written output behind; temporary files of earlier runs that were killed (their
    process is gone) are removed first (:func:`remove_stale_temporaries`; ``clean=False`` skips
    that directory scan, for callers writing many small files into one directory that clean it
    themselves).

    Raises
    ------
    DataFormatError
        If the temporary file cannot be created, the data cannot be written (disk full, quota,
        read-only file system, I/O error) or cannot be moved onto ``path``; the message names
        ``path``.
    """
    target = Path(path)
    make_output_dir(target.parent)
    if target.is_dir():
        raise DataFormatError("is a directory; give a file name", target)
    sfx = target.suffix if suffix is None else suffix
    if clean:
        remove_stale_temporaries(target, sfx)
    try:
        fd, tmp = tempfile.mkstemp(
            prefix=f".{target.name}.{os.getpid()}-{_host_tag()}.", suffix=f".tmp{sfx}", dir=target.parent
        )
    except OSError as exc:
        raise write_error(exc, target, "cannot create a temporary file beside it") from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; outputs follow the umask
        yield tmp_path
        try:
            os.replace(tmp_path, target)
        except OSError as exc:
            raise write_error(exc, target) from None
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        if _is_write_failure(exc):
            raise write_error(exc, target) from None  # type: ignore[arg-type]
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "w", *, clean: bool = True,
                **kwargs: object) -> Iterator[IO]:
    """Open a temporary file for writing that atomically replaces ``path`` when closed cleanly.

    ``clean`` as for :func:`atomic_path`; other keyword arguments go to :func:`open`.

    Raises
    ------
    DataFormatError
        If writing fails (disk full ...): the message names ``path``, which is left untouched.
    """
    with atomic_path(path, clean=clean) as tmp:
        with open(tmp, mode, **kwargs) as fh:  # type: ignore[call-overload]
            yield fh
            try:
                fh.flush()
                os.fsync(fh.fileno())
            except OSError as exc:
                raise write_error(exc, path) from None


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, *, clean: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (``clean`` as for :func:`atomic_path`)."""
    with atomic_open(path, "wb", clean=clean) as fh:
        fh.write(data)


def atomic_write_text(path: str | os.PathLike[str], text: str, *, clean: bool = True) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (``clean`` as for :func:`atomic_path`)."""
    with atomic_open(path, "w", clean=clean, encoding="utf-8") as fh:
        fh.write(text)


# ---------------------------------------------------------------------------- directories
def temp_dir_beside(path: str | os.PathLike[str], *, suffix: str = ".tmp") -> Path:
    """A new, empty directory ``.{name}.{random}{suffix}`` beside ``path`` (its parent created if needed).

    Raises
    ------
    OSError
        If the directory cannot be created (the caller names what failed).
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=suffix, dir=target.parent))


def _move_aside(path: Path) -> Path:
    """Rename ``path`` to ``old`` inside a new ``.{name}.{random}.old`` directory beside it; returns that."""
    trash = temp_dir_beside(path, suffix=".old")
    os.replace(path, trash / "old")
    return trash


def replace_output(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
    """Move ``src`` (a directory or file) onto ``dst`` with renames only, replacing what ``dst`` holds.

    An existing ``dst`` is renamed aside first and deleted once ``src`` is in place (renamed back
    if that fails), so ``dst`` is at every moment either the old or the new output.

    Raises
    ------
    OSError
        If a rename fails (the caller names what failed).
    """
    src, dst = Path(src), Path(dst)
    if not (dst.exists() or dst.is_symlink()):
        os.replace(src, dst)
        return
    trash = _move_aside(dst)
    try:
        os.replace(src, dst)
    except BaseException:
        os.replace(trash / "old", dst)
        with contextlib.suppress(OSError):
            os.rmdir(trash)  # empty again; were the old output not back, it would stay here
        raise
    shutil.rmtree(trash, ignore_errors=True)


def remove_output(path: str | os.PathLike[str]) -> None:
    """Delete an output: a directory is renamed aside first (never half-deleted in place), a file or
    link unlinked; nothing happens if ``path`` does not exist.

    Raises
    ------
    OSError
        If the rename or the unlink fails.
    """
    p = Path(path)
    if not p.exists() and not p.is_symlink():
        return
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(_move_aside(p), ignore_errors=True)
    else:
        p.unlink()


def remove_stale_dirs(path: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary directories that killed writers of ``path`` left beside it.

    Call only while holding the target's :class:`WriterLock`: no other writer of ``path`` then
    runs, so every ``.{name}.{random}.tmp`` / ``.old`` directory beside it (new outputs being
    built, replaced ones being deleted; ``.{name}.old-{pid}`` of earlier versions) is left over.

    Returns
    -------
    list of Path
        The directories removed.
    """
    p = Path(os.path.abspath(path))
    pattern = re.compile(rf"\.{re.escape(p.name)}\.(?:{_RANDOM}\.(?:tmp|old)|old-\d+)")
    try:
        names = os.listdir(p.parent)
    except OSError:
        return []
    removed = []
    for name in names:
        d = p.parent / name
        if pattern.fullmatch(name) and d.is_dir() and not d.is_symlink():
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
    return removed


# ---------------------------------------------------------------------------- writer lock
class WriterLock:
    """Exclusive claim of one output (file or store directory) by one writer.

    The lock file ``.{name}.lock`` beside ``target`` is locked with ``flock`` for as long as the
    writer holds it and records ``{"pid": ..., "host": ...}``.  A second writer on the same
    target gets a :class:`~sonarmap.errors.DataFormatError` naming the holder; a lock file left by
    a writer that died (nobody holds the ``flock``) is taken over.  The lock file is removed on
    :meth:`release`.

    Parameters
    ----------
    target : path-like
        The output to claim.

    Examples
    --------
    >>> with WriterLock("survey.zarr"):  # doctest: +SKIP
    ...     write_the_store()
    """

    def __init__(self, target: str | os.PathLike[str]) -> None:
        self.target = Path(target)
        full = Path(os.path.abspath(self.target))  # "." or "x/.." have a name only once resolved
        self.path = full.parent / f".{full.name}.lock"
        self._fd: int | None = None
        self._pid = 0  # the process that holds it (a forked child must not release it)

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._fd is not None

    def acquire(self) -> WriterLock:
        """Claim the target.

        Raises
        ------
        DataFormatError
            If another writer (a live process) holds the target, or the lock file cannot be
            created.
        """
        if self._fd is not None:
            return self
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise write_error(exc, self.target, "cannot create the output directory") from None
        for _ in range(20):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            except OSError as exc:
                raise write_error(exc, self.path, "cannot create the lock file") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = _read_holder(fd)
                os.close(fd)
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise DataFormatError(
                        f"in use by another writer ({holder}); wait for it to finish or stop it", self.target
                    ) from None
                raise write_error(exc, self.path, "cannot lock") from None
            # The holder before us may have removed the file after we opened it: lock the live one.
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            try:
                os.ftruncate(fd, 0)
                os.write(fd, (json.dumps({"pid": os.getpid(), "host": socket.gethostname()}) + "\n").encode())
            except OSError as exc:
                os.close(fd)
                raise write_error(exc, self.path, "cannot write the lock file") from None
            self._fd, self._pid = fd, os.getpid()
            return self
        raise DataFormatError("lock file keeps changing; is another writer starting?", self.target)

    def release(self) -> None:
        """Give the target up (idempotent)."""
        fd, self._fd = self._fd, None
        if fd is None or self._pid != os.getpid():
            return
        try:
            with contextlib.suppress(OSError):
                if os.path.samestat(os.fstat(fd), os.stat(self.path)):
                    os.unlink(self.path)
        finally:
            os.close(fd)

    def __enter__(self) -> WriterLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:  # pragma: no cover - a writer dropped without closing
        with contextlib.suppress(Exception):
            self.release()


def _read_holder(fd: int) -> str:
    """``"pid N on host H"`` from a lock file (what its writer recorded)."""
    try:
        raw = os.pread(fd, 4096, 0)
        d = json.loads(raw.decode("utf-8"))
        pid, host = int(d["pid"]), str(d["host"])
    except (OSError, ValueError, KeyError, TypeError):
        return "a process that has not recorded its pid yet"
    return f"pid {pid} on host {host}" if host != socket.gethostname() else f"pid {pid}"
