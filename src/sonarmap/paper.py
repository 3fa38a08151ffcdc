"""Reproduction of Teixeira et al. (IROS 2018): Table I, background model (eq. 19), Figs. 2, 3, 5, 6, 8.

Recipes (found by matching the paper's numbers on the shared DIDSON data, see docs/statistics.md):

* **Table I**: ``PreprocessConfig.paper_table1()`` (per-ping PSF, ``1/SNR = 0.001``, *circular*
  Wiener filter, negatives clipped, divided by the per-ping taper, min subtracted and rescaled to
  the input maximum), histogram with ``binning="floor"`` (bins ``[k/256, (k+1)/256)``, the
  authors' ``numpy.histogram``), bounded least squares of eq. 21 with the authors' discretisation
  (``discretization="paper"``).  The exact-normalisation fit and the EM fit are reported beside it.
* **Background** (eq. 19): the 116 background pings pooled, ``PreprocessConfig.paper_background()``
  *with* the per-ping taper division (1/SNR from the files = 0.01, circular, clipped, rescaled to
  the input maximum), floor binning, zero spike + exponential by least squares, exact
  normalisation.
* **Fig. 2** (sonar model, eq. 2-5): the beam pattern ``h`` of the test pings' files, its transfer
  function ``H`` with the Wiener filter ``G`` of their 1/SNR, and the taper ``k(theta)`` of the
  files beside the one estimated from the background pings.
* **Fig. 3** (channel model and pre-processing, eq. 2-7): a hull test ping raw, deconvolved, and
  deconvolved with taper and radial gain, above the background intensity against range with the
  fitted ``k(r) = k1 log10 r + k2 r + k3``.
"""

from __future__ import annotations

import csv
import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._atomic import atomic_open, atomic_path, make_output_dir
from sonarmap.errors import InputError
from sonarmap.stats.mixture import MixtureFit, fit_mixture, histogram

__all__ = [
    "PAPER_TABLE1",
    "PAPER_BACKGROUND",
    "TABLE1_TOLERANCE",
    "Table1Row",
    "table1_config",
    "background_config",
    "table1",
    "background_fit",
    "background_counts",
    "write_paper_outputs",
    "PAPER_OUTPUTS",
    "FIG3_IMAGE",
]

#: Paper Table I: image -> (pi1, lambda, pi2, sigma, KLD).
PAPER_TABLE1: tuple[tuple[float, float, float, float, float], ...] = (
    (0.292, 58.521, 0.021, 0.131, 1.158e-3),
    (0.301, 42.013, 0.015, 0.149, 0.764e-3),
    (0.294, 46.006, 0.016, 0.133, 0.565e-3),
    (0.294, 39.358, 0.014, 0.138, 0.610e-3),
    (0.298, 50.565, 0.011, 0.176, 1.289e-3),
    (0.291, 73.630, 0.020, 0.101, 0.665e-3),
    (0.312, 52.937, 0.000, 1.000, 4.990e-3),
    (0.279, 26.978, 0.070, 0.152, 7.522e-3),
    (0.312, 35.356, 0.006, 0.275, 1.612e-3),
    (0.310, 44.012, 0.010, 0.191, 1.550e-3),
)
#: Paper background model (eq. 19): pi_B, lambda, KLD.
PAPER_BACKGROUND = (0.312, 44.6, 4.06e-4)
#: Acceptance tolerances: (abs pi1, rel lambda, abs pi2, rel sigma, rel KLD).
TABLE1_TOLERANCE = (0.003, 0.03, 0.002, 0.03, 0.5)


def table1_config() -> Any:
    """Pre-processing of Table I (``PreprocessConfig.paper_table1()``)."""
    from sonarmap.preprocess.pipeline import PreprocessConfig

    return PreprocessConfig.paper_table1()


def background_config() -> Any:
    """Pre-processing of the background statistics: ``paper_background()`` plus taper division.

    Without the taper division lambda comes out 42.4 (paper 44.6, -5 %); with it 44.6.
    """
    from sonarmap.preprocess.pipeline import PreprocessConfig

    return PreprocessConfig.paper_background().replace(taper=True, name="paper-background-taper")


@dataclasses.dataclass(frozen=True, eq=False)
class Table1Row:
    """One Table I image: the paper-style fit, the exact-normalisation fit and the EM fit."""

    image: int
    source: str
    paper: MixtureFit
    exact: MixtureFit
    em: MixtureFit

    @staticmethod
    def cells(fit: MixtureFit) -> tuple[float, float, float, float, float]:
        """``(pi1, lambda, pi2, sigma, KLD)`` of a spike + exponential + Rayleigh fit."""
        return (float(fit.weights[1]), 1.0 / fit.params[1][0], float(fit.weights[2]),
                fit.params[2][0], fit.kld)

    def within_tolerance(self) -> tuple[bool, bool, bool, bool, bool]:
        """Whether each paper-style cell is within :data:`TABLE1_TOLERANCE` of the paper."""
        ours = self.cells(self.paper)
        ref = PAPER_TABLE1[self.image]
        tol = TABLE1_TOLERANCE
        return (
            abs(ours[0] - ref[0]) <= tol[0] + 1e-9,
            abs(ours[1] / ref[1] - 1) <= tol[1],
            abs(ours[2] - ref[2]) <= tol[2] + 1e-9,
            abs(ours[3] / ref[3] - 1) <= tol[3],
            abs(ours[4] / ref[4] - 1) <= tol[4],
        )


def _preprocessed(ping: Any, config: Any) -> NDArray[np.float32]:
    from sonarmap.preprocess.pipeline import preprocess_image

    return preprocess_image(ping.image, ping.geometry, config)


def table1(data_dir: str | os.PathLike[str]) -> list[Table1Row]:
    """Fit every test ping (images 0-9 sorted by time stamp) as in the paper's Table I.

    Parameters
    ----------
    data_dir : path-like
        The DIDSON folder holding ``test/`` (``../shared/data/didson``).
    """
    from sonarmap.io.pngjson import iter_png_pings

    test = Path(data_dir) / "test"
    if not test.is_dir():
        raise InputError(f"data: {test} is not a directory (expected <didson>/test)")
    cfg = table1_config()
    rows = []
    for i, ping in enumerate(iter_png_pings(sorted(test.glob("*_raw.png")))):
        img = _preprocessed(ping, cfg)
        counts = histogram(img, 256, binning="floor")
        paper = fit_mixture(counts, method="lsq", binning="floor", discretization="paper")
        exact = fit_mixture(counts, method="lsq", binning="floor")
        em = fit_mixture(counts, method="em", binning="floor")
        rows.append(Table1Row(i, ping.source, paper, exact, em))
    return rows


def background_counts(data_dir: str | os.PathLike[str], *, config: Any = None) -> NDArray[np.float64]:
    """Pooled 256-bin floor histogram of the pre-processed background pings."""
    return _segment_counts(_background_pings(data_dir), background_config() if config is None else config,
                           1)[0]


def _background_pings(data_dir: str | os.PathLike[str]) -> list[Any]:
    """The background pings of the DIDSON folder ``data_dir`` (read once for every output)."""
    from sonarmap.io.pngjson import iter_png_pings

    bg = Path(data_dir) / "background"
    if not bg.is_dir():
        raise InputError(f"data: {bg} is not a directory (expected <didson>/background)")
    return list(iter_png_pings(bg))


def _segment_counts(pings: list[Any], config: Any, segments: int) -> NDArray[np.float64]:
    """Floor histograms ``(segments, 256)`` of the pre-processed pings, pooled per range segment
    (``np.array_split`` of the rows); their sum over segments is the pooled histogram."""
    counts = np.zeros((segments, 256))
    for ping in pings:
        for s, block in enumerate(np.array_split(_preprocessed(ping, config), segments, axis=0)):
            counts[s] += histogram(block, 256, binning="floor")
    return counts


def background_fit(counts: NDArray[np.float64], *, method: str = "lsq") -> MixtureFit:
    """The eq.-19 model ``(1 - pi_B) delta + pi_B Exp(lambda)`` fitted to pooled counts."""
    return fit_mixture(counts, families=("exponential",), method=method, binning="floor")  # type: ignore[arg-type]


def _fmt(v: float) -> str:
    return f"{v:.6g}"


#: Files written by :func:`write_paper_outputs`.
PAPER_OUTPUTS = ("table1.csv", "background.csv", "fig2.png", "fig3.png", "fig5.png", "fig6.png", "fig8.png")
#: Test image (index in Table I) shown pre-processed in Fig. 3: a hull.
FIG3_IMAGE = 4


def write_paper_outputs(data_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Write :data:`PAPER_OUTPUTS`: Table I and the background fit as CSV, Figs. 2, 3, 5, 6 and 8.

    Returns a summary dict (the rows and the background fit).
    """
    out = make_output_dir(out_dir)
    rows = table1(data_dir)
    cols = ["image", "source", "pi1", "lambda", "pi2", "sigma", "kld", "flags",
            "paper_pi1", "paper_lambda", "paper_pi2", "paper_sigma", "paper_kld", "within_tolerance",
            "exact_pi1", "exact_lambda", "exact_pi2", "exact_sigma", "exact_kld", "exact_flags",
            "em_pi1", "em_lambda", "em_pi2", "em_sigma", "em_kld", "em_flags"]
    with atomic_open(out / "table1.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in rows:
            w.writerow([r.image, Path(r.source).name]
                       + [_fmt(v) for v in Table1Row.cells(r.paper)] + [";".join(sorted(r.paper.flags))]
                       + [_fmt(v) for v in PAPER_TABLE1[r.image]] + [all(r.within_tolerance())]
                       + [_fmt(v) for v in Table1Row.cells(r.exact)] + [";".join(sorted(r.exact.flags))]
                       + [_fmt(v) for v in Table1Row.cells(r.em)] + [";".join(sorted(r.em.flags))])
    background = _background_pings(data_dir)
    seg_counts = _segment_counts(background, background_config(), 4)  # Fig. 5's segments
    counts = seg_counts.sum(axis=0)  # integer counts: the same pooled histogram, exactly
    bfit = background_fit(counts)
    bem = background_fit(counts, method="em")
    with atomic_open(out / "background.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["method", "pi_B", "lambda", "kld", "paper_pi_B", "paper_lambda", "paper_kld",
                    "n_pixels", "flags"])
        for f in (bfit, bem):
            w.writerow([f.method, _fmt(f.weights[1]), _fmt(1 / f.params[1][0]), _fmt(f.kld),
                        *PAPER_BACKGROUND, int(f.n_samples), ";".join(sorted(f.flags))])
    _figures(out, rows, bfit, seg_counts)
    _sonar_model_figures(data_dir, out, background)
    return {"rows": rows, "background": bfit, "background_em": bem}


def _figures(out: Path, rows: list[Table1Row], bfit: MixtureFit, seg_counts: NDArray[np.float64]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sonarmap.stats.roc import roc_curve

    # Fig. 5: background histograms per range segment with the pooled model
    segs = seg_counts.shape[0]
    fig, axes = plt.subplots(1, segs, figsize=(4 * segs, 3.2), sharey=True)
    model = bfit.pmf()
    for s, ax in enumerate(axes):
        p = seg_counts[s] / seg_counts[s].sum()
        ax.semilogy(bfit.levels, np.where(p > 0, p, np.nan), ".", ms=3, label="histogram")
        ax.semilogy(bfit.levels, model, "-", label="eq. 19 model")
        ax.set_title(f"range segment {s + 1}/{segs}")
        ax.set_xlabel("intensity")
        ax.set_xlim(0, 0.3)
        ax.set_ylim(1e-8, 1.5)  # the pooled histogram's smallest non-zero bin is ~1e-7
    axes[0].set_ylabel("pmf")
    axes[0].legend()
    fig.tight_layout()
    with atomic_path(out / "fig5.png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    # Fig. 6: ROC per test ping; Fig. 8: histogram + fitted mixture per test ping
    fig6, ax6 = plt.subplots(figsize=(5, 4.5))
    fig8, axes8 = plt.subplots(2, 5, figsize=(18, 6.5), sharey=True)
    for r in rows:
        f = r.paper
        if "no_object" not in f.flags:
            roc = roc_curve(f)
            ax6.plot(roc.pfa, roc.pd, label=f"image {r.image} (AUC {roc.auc:.3f})")
        else:
            # the fit has no object class (image 6, the rudder): no ROC to draw, but the legend says so
            # so that the figure accounts for every ping of Table I
            ax6.plot([], [], " ", label=f"image {r.image}: no object class fitted (no ROC)")
        ax = axes8.flat[r.image]
        p = f.empirical_pmf()
        ax.semilogy(f.levels, np.where(p > 0, p, np.nan), ".", ms=3, label="histogram")
        ax.semilogy(f.levels, f.pmf(), "-", label="LSQ (paper)")
        ax.semilogy(r.em.levels, r.em.pmf(), "--", label="EM")
        ax.set_title(f"image {r.image}" + (" (no object)" if "no_object" in f.flags else ""))
        ax.set_ylim(1e-7, 1)
        ax.set_xlabel("intensity")
    for ax in axes8[:, 0]:
        ax.set_ylabel("pmf")
    ax6.set_xscale("log")
    ax6.set_xlim(1e-12, 1.0)
    ax6.set_xlabel("pFA")
    ax6.set_ylabel("pD")
    ax6.legend(fontsize=7)
    axes8.flat[0].legend(fontsize=7)
    for fig, name in ((fig6, "fig6.png"), (fig8, "fig8.png")):
        fig.tight_layout()
        with atomic_path(out / name) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        plt.close(fig)


def _sonar_model_figures(data_dir: str | os.PathLike[str], out: Path, background: list[Any]) -> None:
    """Figs. 2 and 3: the sonar model (eq. 2-5) and the channel model with pre-processing (eq. 6-7),
    from the test pings of ``data_dir`` and the ``background`` pings."""
    from sonarmap.io.pngjson import iter_png_pings
    from sonarmap.plots import save_figure

    tests = list(iter_png_pings(sorted((Path(data_dir) / "test").glob("*_raw.png"))))
    if not tests or not background:
        raise InputError(f"data: {data_dir} has no test or background pings for Figs. 2 and 3")
    from sonarmap.preprocess.gain import estimate_radial_gain, estimate_taper, intensity_profile

    taper = estimate_taper(background)
    gain = estimate_radial_gain(background, taper=taper)
    level, count, _ = intensity_profile(background, taper)
    pixel_mean = estimate_taper(background, estimator="mean")
    save_figure(_fig2(tests[0].geometry, taper, pixel_mean), out / "fig2.png", dpi=110)
    save_figure(_fig3(tests[min(FIG3_IMAGE, len(tests) - 1)], gain, level, count), out / "fig3.png", dpi=110)


def _fig2(geometry: Any, taper: Any, pixel_mean: Any) -> Any:
    """Fig. 2: beam pattern ``h`` (eq. 2), ``|H|`` and the Wiener ``|G|`` (eq. 3-4), taper (eq. 5):
    the files' taper, the non-zero-mean estimate (``taper``, the one calibration uses) and the
    pixel-mean estimate (``pixel_mean``, which reproduces the files')."""
    from sonarmap.plots import new_figure
    from sonarmap.preprocess.deconvolution import fft_length, wiener_filter

    g = geometry
    fig, (ax_h, ax_f, ax_k) = new_figure(1, 3, figsize=(15.0, 4.0))
    if g.psf_raw is None:
        raise InputError(f"geometry '{g.name}': no beam pattern (psf) for Fig. 2")
    h = np.asarray(g.psf_raw, dtype=np.float64)
    offset = np.arange(h.size) - h.size // 2
    ax_h.stem(offset, h / h.max(), basefmt=" ")
    ax_h.set_xlabel("beam offset from the beam's own centre")
    ax_h.set_ylabel("h (peak = 1)")
    ax_h.set_title("beam pattern across beams (eq. 2)", fontsize=9)
    n_fft = fft_length(h.size, edge="pad")
    freq = np.fft.rfftfreq(n_fft)
    H = np.abs(np.fft.rfft(h / h.sum(), n_fft))
    G = np.abs(wiener_filter(h, noise=g.noise, edge="pad", n_fft=n_fft))
    ax_f.semilogy(freq, H, label="|H| beam pattern")
    ax_f.semilogy(freq, G, label=f"|G| Wiener, 1/SNR = {g.noise:g}")
    ax_f.semilogy(freq, H * G, label="|G H| restored")
    ax_f.set_xlabel("spatial frequency across beams (cycles per beam)")
    ax_f.set_ylabel("gain")
    ax_f.set_title("transfer functions (eq. 3-4)", fontsize=9)
    ax_f.set_ylim(0.03, 300.0)  # room for the legend above the curves
    ax_f.legend(fontsize=7, loc="upper center", ncols=2)
    az = np.rad2deg(g.azimuth_rad)
    if g.taper is not None:
        ax_k.plot(az, g.taper / g.taper.max(), label="k(theta) of the ping files")
    est = taper.taper / taper.taper.max()
    ax_k.plot(az, est, label=f"non-zero mean of {taper.n_images} background pings")
    ax_k.fill_between(az, est * (1 - taper.spread), est * (1 + taper.spread), alpha=0.25,
                      label="its spread over range blocks")
    ax_k.plot(az, pixel_mean.taper / pixel_mean.taper.max(), "--",
              label=f"pixel mean of {pixel_mean.n_images} background pings")
    ax_k.set_xlabel("beam azimuth (deg, positive to starboard)")
    ax_k.set_ylabel("k(theta) (max = 1)")
    ax_k.set_ylim(0.0, 1.6)
    ax_k.set_title("taper: angle-varying gain (eq. 5)", fontsize=9)
    ax_k.legend(fontsize=7, loc="upper center", ncols=2)
    for ax in (ax_h, ax_f, ax_k):
        ax.grid(alpha=0.3)
    fig.suptitle(f"Fig. 2 - sonar model of the DIDSON test pings ({g.n_beams} beams)", fontsize=10)
    return fig


def _fig3(ping: Any, gain: Any, level: NDArray[np.float64], count: NDArray[np.int64]) -> Any:
    """Fig. 3: a test ping raw, deconvolved, deconvolved + taper + radial gain (eq. 2-7), and the
    background intensity against range with the fitted channel model (eq. 6-7)."""
    from sonarmap.plots import draw_fan, new_figure
    from sonarmap.preprocess.gain import radial_gain_db
    from sonarmap.preprocess.pipeline import PreprocessConfig

    g = ping.geometry
    fig, axes = new_figure(2, 3, figsize=(15.0, 9.0), height_ratios=(3, 2))
    steps = (
        ("raw", ping.image),
        ("deconvolved (eq. 3-4)", _preprocessed(ping, PreprocessConfig(taper=False))),
        ("deconvolved, taper and radial gain (eq. 3-7)", _preprocessed(ping, PreprocessConfig(radial_gain=gain))),
    )
    for ax, (title, img) in zip(axes[0], steps, strict=True):
        draw_fan(ax, img, g, title=title, colorbar=False)
    for ax in axes[1, 1:]:
        ax.remove()
    ax = fig.add_subplot(axes[1, 0].get_gridspec()[1, :])
    axes[1, 0].remove()
    r = g.range_m
    ok = (count > 0) & np.isfinite(level) & (level > 0)
    ax.plot(r[ok], 10 * np.log10(level[ok]), ".", ms=3, label="background intensity (116 pings)")
    c = float(np.mean(10 * np.log10(level[ok]) + radial_gain_db(r[ok], gain)))
    ax.plot(r, c - radial_gain_db(r, gain), "-",
            label=(f"channel model: k1 = {gain.k1:.2f} dB/decade, k2 = {gain.k2:.3f} dB/m, "
                   f"rms {gain.rms_db:.2f} dB"))
    ax.set_xlabel("range (m)")
    ax.set_ylabel("intensity (dB)")
    ax.set_title("background level against range; k(r) = k1 log10 r + k2 r + k3 flattens it (eq. 6-7)",
                 fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(f"Fig. 3 - pre-processing of test image {FIG3_IMAGE} ({Path(ping.source).name})", fontsize=10)
    return fig
