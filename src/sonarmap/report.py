"""Self-contained HTML report of a processed survey (``sonarmap report``).

One HTML file with inline CSS and the figures embedded as base64 PNG - no scripts, no external
assets - so it can be mailed, archived or opened offline.  Sections: survey summary and
provenance, mixture-parameter and KLD time series, per-beam ranges over time, the returns' range
uncertainty and detection probability per beam, ROC curves,
flagged pings, example pings as fans (raw | pre-processed or background-normalised | segmented with ranges) and, when the
survey holds registered points, a map preview.
"""

from __future__ import annotations

import base64
import dataclasses
import html
import io
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._atomic import atomic_write_text
from sonarmap.errors import DataFormatError
from sonarmap.ping import source_file, source_name
from sonarmap.survey import flagged_mask

__all__ = ["ReportConfig", "build_report", "render_report"]


@dataclasses.dataclass(frozen=True)
class ReportConfig:
    """What goes into the report.

    Parameters
    ----------
    n_examples : int
        Example pings drawn as fans (the first flagged ping, then evenly spaced ones); their
        source files must still exist (missing ones are skipped with a note).
    max_flagged_rows : int
        Rows of the flagged-ping table.
    max_map_points : int
        Points drawn in the map preview (evenly subsampled).
    dpi : int
        Figure resolution.
    title : str, optional
        Page title (default: the store name).
    """

    n_examples: int = 3
    max_flagged_rows: int = 50
    max_map_points: int = 200_000
    dpi: int = 80
    title: str | None = None

    def __post_init__(self) -> None:
        for name in ("n_examples", "max_flagged_rows", "max_map_points", "dpi"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (1 if name == "dpi" else 0):
                raise ValueError(f"{name}: must be a non-negative integer (got {v!r})")


# ---------------------------------------------------------------------------- figure helpers

def _metres(v: object) -> str:
    """A range in metres for the summary table (3 decimals: mm), or "?"."""
    try:
        return f"{float(v):.3f}"  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return "?"

def _png(fig: Any, dpi: int) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _img(b64: str, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">'


def _times(ds: Any) -> np.ndarray:
    return ds["ping_time"].values.astype("datetime64[ns]")


def _time_axis(ax: Any) -> None:
    import matplotlib.dates as mdates

    loc = mdates.AutoDateLocator()
    ax.xaxis.set_major_locator(loc)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(loc))


#: A mixture component's scale is drawn only where its weight is at least this: a component that
#: holds almost no pixels (an object class on a ping without objects) has an undetermined scale.
MIN_SCALE_WEIGHT = 0.005


def component_scales(param: NDArray[np.floating], weight: NDArray[np.floating]) -> NDArray[np.float64]:
    """Per ping and mixture component, the scale the report draws: the component's last finite
    parameter (``param``, shape (n_pings, n_components, n_params)), NaN where it has none or where
    the component's ``weight`` (n_pings, n_components) is below :data:`MIN_SCALE_WEIGHT`."""
    p = np.asarray(param, dtype=np.float64)
    out = np.full(p.shape[:2], np.nan)
    for i, c in np.ndindex(*p.shape[:2]):
        v = p[i, c][np.isfinite(p[i, c])]
        if v.size and weight[i, c] >= MIN_SCALE_WEIGHT:
            out[i, c] = v[-1]
    return out


def chance_diagonal(n: int = 200) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The ROC of a classifier at chance, ``pD = pFA``, sampled densely enough (0, then ``n``
    points log-spaced from 1e-4 to 1) to be drawn as a line on the report's log-scaled pFA axis
    (two end points would be joined by a straight segment in display space)."""
    x = np.concatenate([[0.0], np.geomspace(1e-4, 1.0, n)])
    return x, x.copy()


#: Time series of at most this many pings draw a marker per ping.
FEW_PINGS = 50


def _fig_timeseries(ds: Any, dpi: int) -> str:
    from sonarmap.plots import new_figure

    t = _times(ds)
    # pings without a time span (one ping, or a recording without a clock): drawn by index
    by_index = t.size < 2 or t.min() == t.max()
    x = np.arange(t.size) if by_index else t
    w = np.atleast_2d(ds["mixture_weight"].values)
    p = ds["mixture_param"].values
    names = str(ds["mixture_weight"].attrs.get("components", "")).split()
    names = names if len(names) == w.shape[1] else [f"component {i}" for i in range(w.shape[1])]
    kld = ds["kld"].values
    flagged = flagged_mask(ds["flags"].values)
    fig, axes = new_figure(3, 1, figsize=(10, 7.5), sharex=True)
    # a marker per ping where the pings are few (a single ping drew no line at all)
    few = {"marker": "o", "ms": 3} if x.size <= FEW_PINGS else {}
    for c in range(w.shape[1]):
        axes[0].plot(x, w[:, c], lw=0.8, label=names[c], **few)
    axes[0].set_ylabel("weight")
    axes[0].set_ylim(-0.02, 1.02)
    axes[0].legend(fontsize=7, ncol=max(1, w.shape[1]), loc="upper right")
    axes[0].set_title("Mixture weights", fontsize=9)
    if p.ndim == 3 and p.shape[2]:
        scales = component_scales(p, w)
        for c in range(p.shape[1]):
            if not np.isnan(p[:, c, :]).all():
                axes[1].plot(x, scales[:, c], lw=0.8, label=names[c] if c < len(names) else str(c),
                             **(few or {"marker": ".", "ms": 2}))
        axes[1].legend(fontsize=7, loc="upper right")
    axes[1].set_ylabel("scale")
    axes[1].set_title("Mixture component scale parameters (gaps: the component holds < "
                      f"{100 * MIN_SCALE_WEIGHT:g} % of the pixels)", fontsize=9)
    axes[2].plot(x, kld, lw=0.8, color="0.2", label="KLD", **few)
    if flagged.any():
        axes[2].plot(x[flagged], kld[flagged], "o", ms=3, color="tab:red", label="flagged fit")
    axes[2].set_ylabel("KLD (nat)")
    axes[2].set_title("Fit quality: Kullback-Leibler divergence data || model", fontsize=9)
    axes[2].legend(fontsize=7, loc="upper right")
    if by_index:
        from matplotlib.ticker import MaxNLocator

        axes[2].set_xlabel("ping (the pings have no time span)")
        axes[2].xaxis.set_major_locator(MaxNLocator(integer=True))
    else:
        axes[2].set_xlabel("ping time (UTC)")
        _time_axis(axes[2])
    return _png(fig, dpi)


def _fig_ranges(ds: Any, dpi: int) -> str:
    from matplotlib.ticker import MaxNLocator

    from sonarmap.plots import new_figure, room_after_colorbar

    r = ds["range"].values
    step = max(1, r.shape[0] // 2000)
    r = r[::step]
    az = np.rad2deg(ds["beam_azimuth"].values) if "beam_azimuth" in ds else np.arange(r.shape[1])
    fig, axes = new_figure(1, 2, figsize=(10, 3.6), width_ratios=[3, 1])
    finite = r[np.isfinite(r)]
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    im = axes[0].imshow(np.ma.masked_invalid(r.T), aspect="auto", origin="lower", cmap="viridis",
                        vmin=vmin, vmax=vmax, interpolation="nearest",
                        extent=(-0.5 * step, (r.shape[0] - 0.5) * step, float(az[0]), float(az[-1])))
    axes[0].xaxis.set_major_locator(MaxNLocator(integer=True))  # ping i is the column centred on i
    axes[0].set_xlabel("ping")
    axes[0].set_ylabel("beam azimuth (deg)")
    axes[0].set_title("Per-beam range over the survey (blank: no return)", fontsize=9)
    fig.colorbar(im, ax=axes[0], label="range (m)")
    room_after_colorbar(fig)
    hit = np.isfinite(ds["range"].values).mean(axis=0)
    axes[1].plot(az, hit, color="tab:blue")
    axes[1].set_xlabel("beam azimuth (deg)")
    axes[1].set_ylabel("fraction of pings")
    axes[1].set_ylim(0, 1.05)  # a fraction of 1 stays visible above the frame
    axes[1].set_title("Beams with a return", fontsize=9)
    return _png(fig, dpi)


def _bin_m(attrs: dict[str, Any]) -> float | None:
    """The range-bin spacing (m) of the survey's sonar from its ``source_geometry`` attribute
    (``(max_range - min_range) / (num_bins - 1)``), None when not recorded or not plausible."""
    try:
        geom = json.loads(attrs.get("source_geometry", "{}"))
        lo, hi, n = float(geom["min_range"]), float(geom["max_range"]), int(geom["num_bins"])
    except (TypeError, ValueError, KeyError, AttributeError, RecursionError):
        return None
    step = (hi - lo) / (n - 1) if n > 1 else math.nan
    return step if math.isfinite(step) and step > 0 else None


def _sigma_summary(ds: Any, bin_m: float | None) -> str:
    """The summary row of the returns' range sigma: median and 5-95 % (cm, and range bins when the
    bin spacing is known); '-' without sigmas."""
    if "range_sigma" not in ds:
        return "-"
    sg = ds["range_sigma"].values
    sg = sg[np.isfinite(sg) & np.isfinite(ds["range"].values)]
    if not sg.size:
        return "-"
    q = np.percentile(sg, [50, 5, 95]) * 100.0
    text = f"{q[0]:.3g} cm (5-95 %: {q[1]:.3g}-{q[2]:.3g} cm)"
    if bin_m is not None:
        text += f"; {q[0] / (100.0 * bin_m):.3g} range bins"
    return text


def _fig_uncertainty(ds: Any, bin_m: float | None, dpi: int) -> str | None:
    """Per beam, the returns' range sigma (median and 16-84 % over the pings) and the median
    detection probability; None when the store holds neither."""
    from sonarmap.plots import new_figure

    have = [k for k in ("range_sigma", "p_detect") if k in ds and np.isfinite(ds[k].values).any()]
    if not have:
        return None
    r = ds["range"].values
    az = np.rad2deg(ds["beam_azimuth"].values) if "beam_azimuth" in ds else np.arange(r.shape[1])
    fig, axes = new_figure(1, 2, figsize=(10, 3.2))
    if "range_sigma" in have:
        sg = np.where(np.isfinite(r), ds["range_sigma"].values, np.nan) * 100.0
        ok = np.isfinite(sg).any(axis=0)
        q = np.full((3, sg.shape[1]), np.nan)
        q[:, ok] = np.nanpercentile(sg[:, ok], [50, 16, 84], axis=0)
        axes[0].fill_between(az, q[1], q[2], color="tab:blue", alpha=0.25, lw=0, label="16-84 % of pings")
        axes[0].plot(az, q[0], color="tab:blue", label="median")
        axes[0].set_ylim(bottom=0)
        axes[0].legend(fontsize=7)
        if bin_m is not None:
            sec = axes[0].secondary_yaxis("right", functions=(lambda v: v / (100.0 * bin_m),
                                                              lambda v: v * 100.0 * bin_m))
            sec.set_ylabel("range bins")
    axes[0].set_xlabel("beam azimuth (deg)")
    axes[0].set_ylabel("range sigma (cm)")
    axes[0].set_title("One-sigma range uncertainty of the returns", fontsize=9)
    if "p_detect" in have:
        pdet = ds["p_detect"].values
        ok = np.isfinite(pdet).any(axis=0)
        med = np.full(pdet.shape[1], np.nan)
        med[ok] = np.nanmedian(pdet[:, ok], axis=0)
        axes[1].plot(az, med, color="tab:green")
    axes[1].set_xlabel("beam azimuth (deg)")
    axes[1].set_ylabel("p_detect, median over pings")
    axes[1].set_ylim(0, 1.05)
    axes[1].set_title("Detection probability per beam", fontsize=9)
    return _png(fig, dpi)


def _roc_of_fit(fit: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """ROC of the intensity threshold under a fitted mixture: (pfa, pd) for thresholds high->low."""
    if not hasattr(fit, "class_pmf"):
        return None
    cp = np.asarray(fit.class_pmf())
    if cp.shape[0] < 2:
        return None
    prior = np.asarray(fit.class_prior())
    obj_w = prior[1:] / prior[1:].sum() if prior[1:].sum() > 0 else np.full(cp.shape[0] - 1, 1 / (cp.shape[0] - 1))
    bg = cp[0]
    obj = obj_w @ cp[1:]
    pfa = np.concatenate([[0.0], np.cumsum(bg[::-1])])
    pd = np.concatenate([[0.0], np.cumsum(obj[::-1])])
    return np.clip(pfa, 0, 1), np.clip(pd, 0, 1)


def _fig_roc(ds: Any, examples: list[dict[str, Any]], dpi: int) -> str | None:
    from sonarmap.plots import new_figure

    pd = ds["pd"].values if "pd" in ds else np.array([])
    pfa = ds["pfa"].values if "pfa" in ds else np.array([])
    ok = np.isfinite(pd) & np.isfinite(pfa)
    curves = [(e["label"], e["roc"]) for e in examples if e.get("roc") is not None]
    if not ok.any() and not curves:
        return None
    fig, ax = new_figure(1, 1, figsize=(5.2, 4.6))
    for label, (x, y) in curves:
        ax.plot(x, y, lw=1.2, label=f"{label} (mixture model)")
    if ok.any():
        ax.scatter(pfa[ok], pd[ok], s=6, c="0.3", alpha=0.5, label="operating point of each ping")
    ax.plot(*chance_diagonal(), ls=":", color="0.6", lw=0.8, label="chance")
    ax.set_xscale("symlog", linthresh=1e-3)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.01)
    ax.set_xlabel("probability of false alarm")
    ax.set_ylabel("probability of detection")
    ax.set_title("ROC of intensity segmentation under the fitted mixtures", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    return _png(fig, dpi)


def _fig_map(ds: Any, max_points: int, dpi: int) -> str | None:
    if "point_xyz" not in ds:
        return None
    from sonarmap.plots import new_figure, room_after_colorbar

    xyz = ds["point_xyz"].values
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if not len(xyz):
        return None
    step = max(1, math.ceil(len(xyz) / max_points))
    xyz = xyz[::step]
    names = ("north x (m)", "east y (m)", "down z (m)")
    span = np.ptp(xyz, axis=0)
    # Main view: the plane of the two largest extents (a hull side seen from abeam, a seafloor
    # from above); colour = the third coordinate.  Second view: from above (x-y).
    h, v = (int(i) for i in np.argsort(span)[::-1][:2])  # horizontal: largest extent
    c = 3 - h - v
    fig, axes = new_figure(1, 2, figsize=(10, 4.6))
    sc = axes[0].scatter(xyz[:, h], xyz[:, v], c=xyz[:, c], s=1.0, cmap="viridis", linewidths=0)
    axes[0].set_aspect("equal", adjustable="datalim")
    axes[0].set_xlabel(names[h])
    axes[0].set_ylabel(names[v])
    if v == 2:
        axes[0].invert_yaxis()  # down is down
    elif h == 2:
        axes[0].invert_xaxis()
    axes[0].set_title(f"Map: {len(xyz)} points, colour = {names[c].split(' (')[0]}", fontsize=9)
    fig.colorbar(sc, ax=axes[0], label=names[c])
    room_after_colorbar(fig)
    top = axes[1].scatter(xyz[:, 1], xyz[:, 0], c=xyz[:, 2], s=1.0, cmap="viridis", linewidths=0)
    axes[1].set_aspect("equal", adjustable="datalim")
    axes[1].set_xlabel(names[1])
    axes[1].set_ylabel(names[0])
    axes[1].set_title("Seen from above (colour = depth)", fontsize=9)
    fig.colorbar(top, ax=axes[1], label=names[2])
    return _png(fig, dpi)


# ---------------------------------------------------------------------------- examples
def _pick_examples(ds: Any, n: int) -> list[int]:
    """The first flagged ping, then pings with returns spread over the survey, then any."""
    if n <= 0:
        return []
    n_p = int(ds.sizes["ping_time"])
    flagged = np.flatnonzero(flagged_mask(ds["flags"].values)).tolist()
    with_returns = np.flatnonzero(np.isfinite(ds["range"].values).any(axis=1))
    picks: list[int] = [int(i) for i in flagged[:1]]
    for pool in (with_returns, np.arange(n_p)):
        if len(pool) == 0:
            continue
        for j in np.linspace(0, len(pool) - 1, n + 2)[1:-1].round().astype(int):
            if len(picks) >= n:
                break
            if int(pool[j]) not in picks:
                picks.append(int(pool[j]))
    return sorted(picks[:n])


def _pipeline_config(attrs: dict[str, Any]) -> Any:
    from sonarmap.pipeline import PipelineConfig

    return PipelineConfig.from_dict(json.loads(attrs.get("pipeline_config", "{}")))


def _calibration(attrs: dict[str, Any]) -> Any:
    """The recording background the run normalised its pings by (the store's ``calibration``
    attribute, written by ``process --calibration``), or None."""
    from sonarmap.preprocess.normalise import RecordingBackground

    text = attrs.get("calibration")
    return None if text is None else RecordingBackground.from_dict(json.loads(text), name="calibration")


#: Fans narrower than this (width over length drawn to scale, :func:`sonarmap.plots.fan_aspect`) are
#: drawn as their polar images in the example pings.
NARROW_FAN = 0.35


def _example(ds: Any, store: str | os.PathLike[str], index: int, config: Any, dpi: int,
             background: Any = None) -> dict[str, Any]:
    """Fans of one ping: raw | pre-processed | segmented with the stored ranges.

    The raw ping is read again from its source by :func:`~sonarmap.store.product_ping`, which
    finds it in a multi-ping file whose stored source names no frame (a store processed from a
    ``sonarmap convert`` store) and checks its time against the stored one.
    """
    from sonarmap.pipeline import process_ping
    from sonarmap.plots import draw_fan, draw_polar, fan_aspect, new_figure
    from sonarmap.store import product_ping

    source = str(ds["source"].values[index])
    label = f"ping {index}"
    if not Path(source_file(source)).exists():
        return {"label": label, "index": index, "source": source, "missing": True}
    ping = product_ping(store, index, image="raw")
    prod = process_ping(ping, config, keep_labels=True, background=background)
    g = ping.geometry
    # a narrow fan drawn to scale is a sliver (an ARIS telephoto lens: 0.30 as wide as long): the
    # images as stored instead, beams across and range up
    polar = fan_aspect(g) < NARROW_FAN

    def panel(ax: Any, image: Any, **kw: Any) -> None:
        if polar:
            draw_polar(ax, image, g, **kw)
        else:
            draw_fan(ax, image, g, colorbar=False, **kw)

    fig, axes = new_figure(1, 3, figsize=(11, 4.6))
    panel(axes[0], ping.image, title="raw")
    # what the classifier saw: the background-normalised image, or the pre-processed one
    normalised = prod.background is not None and prod.background.applied
    title = "background-normalised" if normalised else "pre-processed"
    panel(axes[1], np.clip(prod.image, 0, None), title=title)
    labels = np.asarray(prod.labels) >= 1 if prod.labels is not None else np.zeros(g.shape, bool)
    panel(axes[2], labels.astype(np.float32), vmin=0, vmax=1, cmap="gray", title="segmented + ranges")
    r = ds["range"].values[index]
    az = g.azimuth_rad
    ok = np.isfinite(r)
    if polar:
        axes[2].plot(np.flatnonzero(ok) + 0.5, r[ok], ".", ms=3, color="tab:cyan")
    else:
        axes[2].plot(r[ok] * np.sin(az[ok]), r[ok] * np.cos(az[ok]), ".", ms=3, color="tab:cyan")
    flags = str(ds["flags"].values[index])
    t = np.datetime_as_string(_times(ds)[index], unit="ms")
    fig.suptitle(f"{label}  {t} UTC  KLD {float(ds['kld'].values[index]):.4f}"
                 + (f"  flags: {flags}" if flags else ""), fontsize=9)
    return {"label": label, "index": index, "source": ping.source, "png": _png(fig, dpi),
            "roc": _roc_of_fit(prod.fit)}


# ---------------------------------------------------------------------------- page
_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0 auto;max-width:1100px;
padding:1.5em;color:#1d2330;background:#fff}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.2em;border-bottom:1px solid #dde;padding-bottom:.2em;
margin-top:1.8em}table{border-collapse:collapse;font-size:.85em}td,th{border:1px solid #dde;padding:.25em .6em;
text-align:left;vertical-align:top}th{background:#f3f5fa}img{max-width:100%;height:auto;display:block;
margin:.5em 0}.muted{color:#667}.grid{display:grid;grid-template-columns:1fr 1fr;gap:1em}
pre{background:#f6f8fa;padding:.6em;overflow:auto;font-size:.8em}code{font-size:.9em}
"""


def _row(k: str, v: Any) -> str:
    return f"<tr><th>{html.escape(k)}</th><td>{html.escape(str(v))}</td></tr>"


def _floor_summary(ds: Any) -> str:
    """How many pings were modelled with a quantisation floor (``floor_levels``), and how deep."""
    if "floor_levels" not in ds:
        return "not recorded (a store of an older version)"
    fl = np.asarray(ds["floor_levels"].values, dtype=np.int64)
    used = fl > 0
    if not used.any():
        return "none (every ping modelled as it came)"
    lo, hi = int(fl[used].min()), int(fl[used].max())
    depth = f"{lo} level" + ("" if lo == 1 else "s") if lo == hi else f"{lo}-{hi} levels"
    return f"{int(used.sum())} of {fl.size} pings with their lowest {depth} merged into the zero level"


def _stored_pipeline_config(attrs: dict[str, Any], store: str | os.PathLike[str]) -> dict[str, Any]:
    """The store's ``pipeline_config`` root attribute as a dict; a clean error if it is not one."""
    try:
        pipeline_config = json.loads(attrs.get("pipeline_config", "{}"))
        if not isinstance(pipeline_config, dict):
            raise ValueError("not a JSON object")
    except (TypeError, ValueError, RecursionError) as exc:
        raise DataFormatError(f"root attribute pipeline_config is not a JSON object ({exc})",
                              Path(store) / "zarr.json") from None
    return pipeline_config


def _summary_rows(ds: Any, attrs: dict[str, Any], status: dict[str, Any], t: np.ndarray,
                  n_flagged: int, bin_m: float | None) -> list[tuple[str, Any]]:
    """The (label, value) rows of the report's summary table (``bin_m``: :func:`_bin_m`)."""
    n = int(ds.sizes["ping_time"])
    written = t.astype(np.int64) != 0
    kld = ds["kld"].values
    hit = np.isfinite(ds["range"].values)
    try:
        geom = json.loads(attrs.get("source_geometry", "{}"))
    except ValueError:
        geom = {}
    span = (t[written][-1] - t[written][0]).astype("timedelta64[ms]").astype(float) / 1e3 if written.any() else 0.0
    return [
        ("pings", f"{n}" + ("" if status["complete"] else f" (incomplete: {status['done']}/{status['n_chunks']} chunks)")),
        ("time span", f"{np.datetime_as_string(t[written][0], unit='s')} to "
         f"{np.datetime_as_string(t[written][-1], unit='s')} UTC ({span:.1f} s)" if written.any() else "-"),
        ("flagged fits", f"{n_flagged} ({100 * n_flagged / max(n, 1):.1f} %)"),
        ("KLD median / 95th percentile", f"{np.nanmedian(kld):.4g} / {np.nanpercentile(kld, 95):.4g}"
         if np.isfinite(kld).any() else "-"),
        ("beams with a return", f"{100 * hit.mean():.1f} %"),
        ("range sigma of the returns, median", _sigma_summary(ds, bin_m)),
        ("quantisation floor", _floor_summary(ds)),
        ("sonar", f"{geom.get('name', '?')}: {geom.get('num_beams', '?')} beams x {geom.get('num_bins', '?')} bins, "
         f"{_metres(geom.get('min_range'))}-{_metres(geom.get('max_range'))} m"),
        ("input files", attrs.get("n_input_files", "?")),
        ("registered points", int(ds.sizes["point"]) if "point" in ds.sizes else "none (no poses given)"),
        ("sonarmap version", attrs.get("sonarmap_version", "?")),
        ("fingerprint", attrs.get("fingerprint", "?")),
    ]


def _draw_examples(ds: Any, store: str | os.PathLike[str], attrs: dict[str, Any],
                   cfg: ReportConfig) -> tuple[list[dict[str, Any]], list[str]]:
    """Re-process the example pings; returns the drawn examples and a note for each one not drawn."""
    examples: list[dict[str, Any]] = []
    notes: list[str] = []
    picks = _pick_examples(ds, cfg.n_examples)
    if picks:
        try:
            pcfg, background = _pipeline_config(attrs), _calibration(attrs)
        except Exception as exc:  # noqa: BLE001
            pcfg = None
            notes.append(f"example pings not drawn: pipeline unavailable ({exc})")
        if pcfg is not None:
            for i in picks:
                try:
                    examples.append(_example(ds, store, i, pcfg, cfg.dpi, background))
                except Exception as exc:  # noqa: BLE001 - keep the rest of the report
                    notes.append(f"ping {i}: not drawn ({type(exc).__name__}: {exc})")
    return examples, notes


def _flagged_section(ds: Any, flagged: list[int], flags: list[str], t: np.ndarray, cfg: ReportConfig) -> list[str]:
    """HTML of the flagged-pings section: a table of at most ``cfg.max_flagged_rows`` rows."""
    kld = ds["kld"].values
    parts = [f"<h2>Flagged pings ({len(flagged)})</h2>"]
    if flagged:
        parts.append("<table><tr><th>#</th><th>time (UTC)</th><th>flags</th><th>KLD</th><th>source</th></tr>")
        for i in flagged[: cfg.max_flagged_rows]:
            parts.append(
                f"<tr><td>{i}</td><td>{np.datetime_as_string(t[i], unit='ms')}</td>"
                f"<td>{html.escape(flags[i])}</td><td>{kld[i]:.4g}</td>"
                f"<td>{html.escape(source_name(str(ds['source'].values[i])))}</td></tr>"
            )
        parts.append("</table>")
        if len(flagged) > cfg.max_flagged_rows:
            parts.append(f"<p class='muted'>... and {len(flagged) - cfg.max_flagged_rows} more.</p>")
    else:
        parts.append("<p>No fit was flagged.</p>")
    return parts


def _examples_section(examples: list[dict[str, Any]], notes: list[str]) -> list[str]:
    """HTML of the example-pings section, with a line for each example whose source is gone."""
    parts = ["<h2>Example pings</h2>"]
    for e in examples:
        if e.get("missing"):
            live = "://" in source_file(str(e["source"]))  # tcp:// / oculus://: a live stream
            why = ("was received live and is not stored (the product store holds the products, not the "
                   "images)" if live else "no longer exists")
            parts.append(f"<p class='muted'>{html.escape(e['label'])}: source {html.escape(e['source'])} "
                         f"{why}.</p>")
        else:
            parts.append(f"<h3>{html.escape(e['label'])}: <code>{html.escape(source_name(e['source']))}</code></h3>")
            parts.append(_img(e["png"], e["label"]))
    for note in notes:
        parts.append(f"<p class='muted'>{html.escape(note)}</p>")
    return parts


def render_report(store: str | os.PathLike[str], *, config: ReportConfig | None = None) -> str:
    """The report of survey ``store`` as an HTML string (self-contained).

    Raises
    ------
    DataFormatError
        If ``store`` is not a survey store, or is damaged: corrupt or missing metadata, arrays or
        chunks, or values outside their documented ranges (:func:`sonarmap.survey.load_products`).
    """
    from sonarmap.survey import load_products, survey_status

    cfg = config or ReportConfig()
    ds = load_products(store)  # metadata, chunks and values checked: a damaged store is one clean error
    status = survey_status(store)
    attrs = dict(ds.attrs)
    pipeline_config = _stored_pipeline_config(attrs, store)
    t = _times(ds)
    flags = [str(f) for f in ds["flags"].values]
    flagged = np.flatnonzero(flagged_mask(flags)).tolist()
    title = cfg.title or f"Survey report: {Path(store).name}"
    bin_m = _bin_m(attrs)
    summary = _summary_rows(ds, attrs, status, t, len(flagged), bin_m)
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p class='muted'>{html.escape(str(Path(store).resolve()))}</p>",
        "<h2>Summary</h2><table>", *(_row(k, v) for k, v in summary), "</table>",
        "<details><summary>Pipeline configuration</summary><pre>",
        html.escape(json.dumps(pipeline_config, indent=1)),
        "</pre></details>",
        "<h2>Mixture parameters and fit quality</h2>", _img(_fig_timeseries(ds, cfg.dpi), "time series"),
        "<h2>Ranges</h2>", _img(_fig_ranges(ds, cfg.dpi), "ranges over time"),
    ]
    unc = _fig_uncertainty(ds, bin_m, cfg.dpi)
    if unc is not None:
        parts.append(_img(unc, "range uncertainty and detection probability per beam"))
    examples, notes = _draw_examples(ds, store, attrs, cfg)
    roc = _fig_roc(ds, examples, cfg.dpi)
    parts.append("<h2>ROC curves</h2>")
    parts.append(_img(roc, "ROC curves") if roc else "<p class='muted'>No detection statistics stored.</p>")
    parts += _flagged_section(ds, flagged, flags, t, cfg)
    parts += _examples_section(examples, notes)
    mp = _fig_map(ds, cfg.max_map_points, cfg.dpi)
    if mp is not None:
        parts.append("<h2>Map preview</h2>")
        parts.append(_img(mp, "map preview"))
    parts.append(f"<p class='muted'>Generated by sonarmap {html.escape(str(attrs.get('sonarmap_version', '')))}."
                 "</p></body></html>")
    return "\n".join(parts)


def build_report(
    store: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    config: ReportConfig | None = None,
    overwrite: bool = False,
) -> Path:
    """Write the HTML report of ``store`` to ``output`` atomically.

    Raises
    ------
    DataFormatError
        If ``output`` exists and ``overwrite`` is false, or ``store`` is not a survey store.
    """
    out = Path(output)
    if out.exists() and not overwrite:
        raise DataFormatError("output exists; use --overwrite to replace it", out)
    text = render_report(store, config=config)
    atomic_write_text(out, text)
    return out
