"""Exception and warning hierarchy.

Every error raised on purpose by sonarmap derives from :class:`SonarmapError`; each subclass also
derives from the matching builtin so callers may catch either (``except ValueError`` keeps working).
Messages name the file or argument and say what is wrong, in one line.
"""

from __future__ import annotations

import sys

__all__ = [
    "SonarmapError",
    "InputError",
    "GeometryError",
    "DataFormatError",
    "FitError",
    "SonarmapWarning",
    "show_warning_one_line",
]


class SonarmapError(Exception):
    """Root of all sonarmap errors."""


class InputError(SonarmapError, ValueError):
    """An argument has the wrong shape, dtype, range or contains NaN/inf."""


class GeometryError(SonarmapError, ValueError):
    """A sonar geometry is inconsistent (beam counts, ranges, PSF length ...)."""


class DataFormatError(SonarmapError, OSError):
    """A file is missing, unreadable, truncated, corrupt or of an unexpected format.

    Parameters
    ----------
    message : str
        What is wrong.
    path : str or os.PathLike, optional
        The offending file; prefixed to the message.
    offset : int, optional
        Byte offset in the file where the problem was detected.
    """

    def __init__(self, message: str, path: object | None = None, offset: int | None = None) -> None:
        self.path = None if path is None else str(path)
        self.offset = offset
        prefix = ""
        if self.path is not None:
            prefix = f"{self.path}: "
        if offset is not None:
            prefix += f"at byte {offset}: "
        super().__init__(prefix + message)


class FitError(SonarmapError, ValueError):
    """A statistical fit cannot be computed from the data given (not merely degenerate)."""


class SonarmapWarning(UserWarning):
    """Base class of sonarmap warnings."""


def show_warning_one_line(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: object | None = None,
    line: str | None = None,
) -> None:
    """A :func:`warnings.showwarning` that prints ``sonarmap: warning: <message>`` as one line on stderr.

    The CLI installs it for the duration of a command, and the survey's worker processes install
    it too, so that a warning raised while reading a file reads the same wherever it was raised.
    """
    text = " ".join(str(message).split()) or category.__name__
    if not issubclass(category, UserWarning) or category is UserWarning:
        text = f"{category.__name__}: {text}"
    print(f"sonarmap: warning: {text}", file=sys.stderr)
