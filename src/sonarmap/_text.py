"""Wording shared by the command line's and the library's one-line summaries."""

from __future__ import annotations

__all__ = ["counted"]


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` and ``noun``, in the plural unless ``n`` is 1.

    Parameters
    ----------
    n : int
        The count.
    noun : str
        The singular noun.
    plural : str, optional
        The plural when it is not ``noun + "s"``.

    Returns
    -------
    str
        ``"1 ping"``, ``"0 pings"``, ``"3 pings"``.

    Examples
    --------
    >>> counted(1, "ping"), counted(6, "ping"), counted(0, "return")
    ('1 ping', '6 pings', '0 returns')
    >>> counted(2, "reconnect", "reconnects")
    '2 reconnects'
    """
    return f"{n} {noun if n == 1 else (plural or noun + 's')}"
