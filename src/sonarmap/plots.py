"""Matplotlib figures (Agg backend, no screen needed).

All functions return a :class:`matplotlib.figure.Figure`; :func:`save_figure` writes it atomically.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from sonarmap._atomic import atomic_path
from sonarmap.errors import InputError
from sonarmap.fan import fan_image
from sonarmap.ping import Ping, source_name

__all__ = ["new_figure", "recorded_bins", "room_after_colorbar", "save_figure", "draw_fan", "draw_polar", "fan_aspect",
           "show_ping_figure", "fan_comparison", "display_scale",
           "DB_SPAN_RATIO", "DB_WINDOW"]


def new_figure(*args: Any, **kwargs: Any) -> tuple[Any, Any]:
    """``plt.subplots`` on a figure not registered with pyplot (thread/process safe, Agg)."""
    from matplotlib.figure import Figure

    fig = Figure(layout="constrained", **{k: kwargs.pop(k) for k in ("figsize", "dpi") if k in kwargs})
    axes = fig.subplots(*args, **kwargs)
    return fig, axes


def room_after_colorbar(fig: Any) -> None:
    """Space between a colour bar's label and the axis to its right in a figure of
    :func:`new_figure` (the constrained layout's default leaves the two labels touching)."""
    fig.get_layout_engine().set(wspace=0.12)


def save_figure(fig: Any, path: str | os.PathLike[str], *, dpi: int = 120) -> None:
    """Write ``fig`` atomically; the format follows the file extension."""
    fmt = os.path.splitext(str(path))[1].lstrip(".").lower() or "png"
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=fmt)


def draw_fan(
    ax: Any,
    image: np.ndarray,
    geometry: Any,
    *,
    resolution_m: float | None = None,
    cmap: str = "inferno",
    vmin: float | None = 0.0,
    vmax: float | None = None,
    title: str | None = None,
    colorbar: bool = True,
    recorded: np.ndarray | None = None,
) -> Any:
    """Draw a polar image as a fan on ``ax`` with metric axes (starboard right, forward up);
    outside the bins ``recorded`` marks (:func:`recorded_bins`), the fan shows no data."""
    fan = fan_image(image, geometry, resolution_m=resolution_m)
    if recorded is not None:
        seen = fan_image(recorded.astype(np.float32), geometry, resolution_m=resolution_m, order=0).image
        fan.image[~(seen >= 0.5)] = np.nan
    if vmax is None:
        finite = fan.image[np.isfinite(fan.image)]
        vmax = float(np.percentile(finite, 99.9)) if finite.size else 1.0
        vmax = vmax if vmax > 0 else 1.0
    masked = np.ma.masked_invalid(fan.image)
    im = ax.imshow(masked, origin="lower", extent=fan.extent_m, cmap=cmap, vmin=vmin, vmax=vmax,
                   interpolation="nearest")
    ax.set_facecolor("0.85")
    ax.set_aspect("equal")
    ax.set_xlabel("starboard y (m)")
    ax.set_ylabel("forward x (m)")
    if title:
        ax.set_title(title, fontsize=9)
    if colorbar:
        ax.figure.colorbar(im, ax=ax, shrink=0.8, label="intensity")
    return im


#: ``display_scale("auto")`` shows a ping in dB when its positive pixels' 99.9th percentile exceeds
#: this multiple of their median (30 dB): a linear colour scale then shows the brightest 0.1 % on
#: black (a Kongsberg water column spans ~60 dB, 1e6; imaging sonars' 8-bit images 2-20).
DB_SPAN_RATIO = 1000.0
#: Characters of a 9-point title per inch of figure width that :func:`show_ping_figure` puts on one line.
_TITLE_CHARS_PER_INCH = 11
#: The dB display's window below its maximum (dB).
DB_WINDOW = 60.0


def display_scale(image: np.ndarray, scale: str = "auto") -> str:
    """``"linear"`` or ``"db"``: ``scale`` itself, or for ``"auto"`` dB when the image's positive
    pixels span more than :data:`DB_SPAN_RATIO` between their median and 99.9th percentile."""
    if scale not in ("auto", "linear", "db"):
        raise InputError(f"scale: must be auto, linear or db (got {scale!r})")
    if scale != "auto":
        return scale
    pos = image[np.isfinite(image) & (image > 0)]
    if pos.size == 0:
        return "linear"
    return "db" if float(np.percentile(pos, 99.9)) > DB_SPAN_RATIO * float(np.median(pos)) else "linear"


def _in_db(image: np.ndarray, vmax: float | None) -> tuple[np.ndarray, float, float]:
    """``10 log10`` of the image and its colour range: ``vmax`` (dB; default the positive pixels'
    99.9th percentile) down :data:`DB_WINDOW`; pixels <= 0 (or not finite) at the range's bottom."""
    img = np.asarray(image, dtype=np.float64)
    pos = np.isfinite(img) & (img > 0)
    db = np.zeros(img.shape)
    db[pos] = 10.0 * np.log10(img[pos])
    top = vmax if vmax is not None else (float(np.percentile(db[pos], 99.9)) if pos.any() else 0.0)
    db[~pos] = top - DB_WINDOW
    return db.astype(np.float32), top - DB_WINDOW, top


def recorded_bins(image: np.ndarray, meta: dict[str, Any]) -> np.ndarray | None:
    """Where each beam recorded samples: a bool image, or None when every bin was recorded.

    A multibeam's water-column beams end at different ranges (Kongsberg: ``beam_start_sample`` and
    ``beam_n_samples`` per image column in ``Ping.meta``); the reader fills the rest with 0, which a
    figure would otherwise draw as the weakest echo.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        The ping's image.
    meta : dict
        The ping's metadata.

    Returns
    -------
    ndarray of bool, shape (n_bins, n_beams), or None

    Examples
    --------
    >>> img = np.ones((4, 2), np.float32)
    >>> recorded_bins(img, {"beam_start_sample": [0, 1], "beam_n_samples": [4, 2]})[:, 1]
    array([False,  True,  True, False])
    """
    start, count = meta.get("beam_start_sample"), meta.get("beam_n_samples")
    if start is None or count is None or np.shape(start) != (image.shape[1],) or np.shape(count) != np.shape(start):
        return None
    rows = np.arange(image.shape[0])[:, None]
    first = np.asarray(start)[None, :]
    recorded = (rows >= first) & (rows < first + np.asarray(count)[None, :])
    return None if recorded.all() else recorded


def show_ping_figure(
    ping: Ping,
    *,
    resolution_m: float | None = None,
    polar: bool = False,
    vmax: float | None = None,
    scale: str = "auto",
) -> Any:
    """Figure of one ping as a fan, optionally beside its raw polar image.

    ``scale``: ``"linear"``, ``"db"`` (``10 log10`` of the intensity, a :data:`DB_WINDOW` window
    below ``vmax`` in dB, default the 99.9th percentile) or ``"auto"`` (:func:`display_scale`).
    """
    ncols = 2 if polar else 1
    fig, axes = new_figure(1, ncols, figsize=(5.0 * ncols, 6.0), squeeze=False)
    name, when = source_name(ping.source) or "ping", f"{np.datetime_as_string(ping.datetime64, unit='ms')} UTC"
    # over the whole figure (not the fan, beside which the colour bar stands); a long name (a
    # Kongsberg head and ping, a bag topic) puts the time on a line of its own
    one_line = len(name) + len(when) + 2 <= _TITLE_CHARS_PER_INCH * 5.0 * ncols
    fig.suptitle(f"{name}  {when}" if one_line else f"{name}\n{when}", fontsize=9)
    in_db = display_scale(ping.image, scale) == "db"
    img, vmin = ping.image, 0.0
    if in_db:
        img, vmin, vmax = _in_db(ping.image, vmax)
    recorded = recorded_bins(ping.image, ping.meta)
    im = draw_fan(axes[0, 0], img, ping.geometry, resolution_m=resolution_m, vmin=vmin, vmax=vmax,
                  recorded=recorded)
    label = "intensity (dB)" if in_db else "intensity"
    im.colorbar.set_label(label)
    if polar:
        im = draw_polar(axes[0, 1], img, ping.geometry, vmin=vmin, vmax=vmax, recorded=recorded,
                        title="polar (rows = range bins)")
        fig.colorbar(im, ax=axes[0, 1], shrink=0.8, label=label)
        room_after_colorbar(fig)
    return fig


def draw_polar(ax: Any, image: np.ndarray, geometry: Any, *, cmap: str = "inferno", vmin: float | None = 0.0,
               vmax: float | None = None, title: str | None = None, recorded: np.ndarray | None = None) -> Any:
    """Draw a polar image as it is stored: beams across (column ``j`` spans ``[j, j + 1)``), range
    up, in metres; outside the bins ``recorded`` marks, no data (grey, as around a fan)."""
    g = geometry
    az = np.rad2deg(g.azimuth_rad)
    shown = np.ma.masked_array(image, mask=None if recorded is None else ~recorded)
    im = ax.imshow(shown, origin="lower", aspect="auto", cmap=cmap, vmin=vmin, vmax=vmax,
                   extent=(0, g.n_beams, g.range_m[0], g.range_m[-1]))
    ax.set_facecolor("0.85")
    ax.set_xlabel(f"beam (azimuth {az[0]:.1f} to {az[-1]:.1f} deg)")
    ax.set_ylabel("range (m)")
    if title:
        ax.set_title(title, fontsize=9)
    return im


def fan_aspect(geometry: Any) -> float:
    """Width over length of the box a ping's fan is drawn in to scale (:func:`draw_fan`,
    :func:`sonarmap.fan.fan_extent_m`): 0.30 for the shared ARIS telephoto recording (14.6 deg,
    3.3-23.4 m), 0.62 for the DIDSON test pings, 1.0 for the 60 deg Oculus fan from 0 m."""
    from sonarmap.fan import fan_extent_m

    x0, x1, y0, y1 = fan_extent_m(geometry)  # x forward, y starboard
    return (y1 - y0) / (x1 - x0) if x1 > x0 else 1.0


def fan_comparison(
    before: Ping,
    after: Ping,
    *,
    titles: tuple[str, str] = ("raw", "pre-processed"),
    resolution_m: float | None = None,
    vmax: tuple[float | None, float | None] = (None, None),
) -> Any:
    """Fig.-1-style before/after figure: the raw fan beside the corrected fan.

    Each panel has its own colour scale (99.9th percentile unless ``vmax`` is given), since
    pre-processing changes the intensity scale.  The right panel's title lists the steps recorded
    in ``after.meta["preprocess"]`` when present.
    """
    fig, axes = new_figure(1, 2, figsize=(10.0, 6.0), squeeze=False)
    steps = after.meta.get("preprocess", {}).get("steps")
    t_after = titles[1] + (f"\n({', '.join(steps)})" if steps else "")
    draw_fan(axes[0, 0], before.image, before.geometry, resolution_m=resolution_m, vmax=vmax[0],
             title=titles[0])
    draw_fan(axes[0, 1], after.image, after.geometry, resolution_m=resolution_m, vmax=vmax[1],
             title=t_after)
    name = source_name(before.source) or "ping"
    fig.suptitle(name, fontsize=10)
    return fig
