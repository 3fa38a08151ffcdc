"""Compare simulated pings with real recordings (histograms, zero spike, levels vs range, KLD).

Run ``python -m sonarmap.simulate.compare ../shared/data/didson/background`` to print the DIDSON
table quoted in ``docs/simulator.md``; give a recording file instead (``sample.aris``,
``three_pings_8bit.raw``) for the ARIS / Oculus tables, or ``--all`` for all three.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import Ping
from sonarmap.simulate.render import SimulationConfig, iter_simulated_pings, simulate_ping
from sonarmap.simulate.scene import Scene, empty_scene, scene_from_name

__all__ = [
    "BackgroundStats",
    "background_stats",
    "histogram_kld",
    "compare_background",
    "RecordingComparison",
    "compare_recording",
    "recording_comparisons",
    "ghost_ratios",
]


@dataclasses.dataclass(frozen=True)
class BackgroundStats:
    """Pixel statistics of a set of 8-bit pings.

    Attributes
    ----------
    histogram : ndarray, shape (256,)
        Normalised histogram of the 8-bit values.
    zero_fraction, mean, nonzero_mean : float
        Fraction of zero pixels, mean intensity on [0, 1], mean of the non-zero pixels on [0, 1].
    nonzero_rate : float
        Maximum-likelihood exponential rate ``1 / nonzero_mean`` (the paper's lambda).
    range_profile : ndarray, shape (n_bins,)
        Mean intensity per range bin.
    beam_profile : ndarray, shape (n_beams,)
        Mean intensity per beam.
    """

    histogram: NDArray[np.float64]
    zero_fraction: float
    mean: float
    nonzero_mean: float
    nonzero_rate: float
    range_profile: NDArray[np.float64]
    beam_profile: NDArray[np.float64]


def background_stats(images: Iterable[NDArray[np.floating]]) -> BackgroundStats:
    """Statistics of images in [0, 1] that hold 8-bit values (k / 255)."""
    hist = np.zeros(256)
    rsum: NDArray[np.float64] | None = None
    bsum: NDArray[np.float64] | None = None
    n = 0
    for img in images:
        q = np.rint(np.asarray(img, dtype=np.float64) * 255.0).astype(np.int64)
        hist += np.bincount(q.ravel(), minlength=256)[:256]
        rs, bs = q.mean(axis=1) / 255.0, q.mean(axis=0) / 255.0
        rsum = rs if rsum is None else rsum + rs
        bsum = bs if bsum is None else bsum + bs
        n += 1
    if n == 0 or rsum is None or bsum is None:
        from sonarmap.errors import InputError

        raise InputError("images: no images given")
    total = hist.sum()
    h = hist / total
    k = np.arange(256) / 255.0
    nz = float((h[1:] * k[1:]).sum() / h[1:].sum())
    return BackgroundStats(
        histogram=h,
        zero_fraction=float(h[0]),
        mean=float((h * k).sum()),
        nonzero_mean=nz,
        nonzero_rate=1.0 / nz,
        range_profile=rsum / n,
        beam_profile=bsum / n,
    )


def histogram_kld(p: NDArray[np.float64], q: NDArray[np.float64], eps: float = 1e-9) -> float:
    """Kullback-Leibler divergence ``KL(p || q)`` in nats between two 256-bin histograms.

    ``eps`` is added to both before renormalising so empty bins do not give infinities; the
    divergence is the library's eq. 11 (:func:`sonarmap.stats.mixture.kl_divergence`).
    """
    from sonarmap.stats.mixture import kl_divergence

    b = np.asarray(q, dtype=np.float64) + eps
    return kl_divergence(np.asarray(p, dtype=np.float64) + eps, b / b.sum())


def compare_background(
    real: Iterable[Ping], *, config: SimulationConfig = SimulationConfig(), n_sim: int = 116, seed: int = 0
) -> dict[str, float]:
    """Simulate ``n_sim`` open-water pings with the real pings' geometry and compare statistics."""
    real_list = list(real)
    geom = real_list[0].geometry
    rs = background_stats(p.image for p in real_list)
    scene = empty_scene()
    ss = background_stats(
        simulate_ping(scene, geom, config=config, seed=seed + i).ping.image for i in range(n_sim)
    )
    sl = slice(1, None)  # row 0 of the real data is anomalously dark (see docs/simulator.md)
    return {
        "real_zero_fraction": rs.zero_fraction,
        "sim_zero_fraction": ss.zero_fraction,
        "real_mean": rs.mean,
        "sim_mean": ss.mean,
        "real_nonzero_rate": rs.nonzero_rate,
        "sim_nonzero_rate": ss.nonzero_rate,
        "kld_real_sim": histogram_kld(rs.histogram, ss.histogram),
        "kld_sim_sim": histogram_kld(
            ss.histogram,
            background_stats(
                simulate_ping(scene, geom, config=config, seed=10_000 + seed + i).ping.image
                for i in range(n_sim)
            ).histogram,
        ),
        "range_profile_corr": float(np.corrcoef(rs.range_profile[sl], ss.range_profile[sl])[0, 1]),
        "beam_profile_corr": float(np.corrcoef(rs.beam_profile, ss.beam_profile)[0, 1]),
        "real_p_ge_30": float(rs.histogram[30:].sum()),
        "sim_p_ge_30": float(ss.histogram[30:].sum()),
    }


@dataclasses.dataclass(frozen=True)
class RecordingComparison:
    """Simulated pings of one scene against a real recording, over a range window.

    Attributes
    ----------
    label : str
        What was compared (e.g. ``"aris sample.aris vs empty"``).
    scene : str
        Scene simulated.
    geometry_name : str
        Name of the recording's geometry (it selects the sonar profile).
    rows : tuple of int
        First and one-past-last image row compared.
    real, sim : BackgroundStats
        Statistics of the real and the simulated pings over those rows.
    kld_real_sim : float
        ``KL(real || sim)`` of the 256-bin histograms, nats.
    kld_sim_sim : float
        The same between two independent simulated sets (the sampling floor).
    band_range_m : ndarray, shape (n_bands,)
        Centre range of each range band.
    real_percentiles, sim_percentiles : ndarray, shape (n_bands, 3)
        10th, 50th and 90th percentile of the pixel values in each band.
    real_band_mean, sim_band_mean : ndarray, shape (n_bands,)
        Mean pixel value in each band.
    """

    label: str
    scene: str
    geometry_name: str
    rows: tuple[int, int]
    real: BackgroundStats
    sim: BackgroundStats
    kld_real_sim: float
    kld_sim_sim: float
    band_range_m: NDArray[np.float64]
    real_percentiles: NDArray[np.float64]
    sim_percentiles: NDArray[np.float64]
    real_band_mean: NDArray[np.float64]
    sim_band_mean: NDArray[np.float64]

    def summary(self) -> dict[str, float]:
        """Scalar figures: zero fractions, means, medians, KLDs and the near/far background ratio."""
        return {
            "real_zero_fraction": self.real.zero_fraction,
            "sim_zero_fraction": self.sim.zero_fraction,
            "real_mean": self.real.mean,
            "sim_mean": self.sim.mean,
            "real_median": float(np.median(self.real_percentiles[:, 1])),
            "sim_median": float(np.median(self.sim_percentiles[:, 1])),
            "real_near_far_ratio": float(self.real_band_mean[0] / self.real_band_mean[-1]),
            "sim_near_far_ratio": float(self.sim_band_mean[0] / self.sim_band_mean[-1]),
            "kld_real_sim": self.kld_real_sim,
            "kld_sim_sim": self.kld_sim_sim,
        }

    def table(self) -> str:
        """Plain-text table: the summary, then the percentiles and means per range band."""
        lines = [f"{self.label}  (rows {self.rows[0]}-{self.rows[1] - 1}, geometry {self.geometry_name})"]
        lines += [f"  {k:22s} {v:.4f}" for k, v in self.summary().items()]
        lines.append("  range_m    real p10/p50/p90 (mean)       sim p10/p50/p90 (mean)")
        for i, r in enumerate(self.band_range_m):
            rp, sp = self.real_percentiles[i], self.sim_percentiles[i]
            lines.append(
                f"  {r:7.3f}   {rp[0]:.3f}/{rp[1]:.3f}/{rp[2]:.3f} ({self.real_band_mean[i]:.3f})"
                f"   {sp[0]:.3f}/{sp[1]:.3f}/{sp[2]:.3f} ({self.sim_band_mean[i]:.3f})"
            )
        return "\n".join(lines)


def _band_stats(stack: NDArray[np.float64], edges: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    pct = np.array([np.percentile(stack[:, a:b], [10, 50, 90]) for a, b in zip(edges[:-1], edges[1:], strict=True)])
    mean = np.array([stack[:, a:b].mean() for a, b in zip(edges[:-1], edges[1:], strict=True)])
    return pct, mean


def _one_geometry(real: Iterable[Ping]) -> list[Ping]:
    """The pings of ``real``, checked to be at least one and all of one image shape."""
    pings = list(real)
    if not pings:
        raise InputError("real: no pings given")
    geom = pings[0].geometry
    if any(p.image.shape != geom.shape for p in pings):
        raise InputError("real: pings of different shapes; compare one geometry at a time")
    return pings


def _row_window(geom: SonarGeometry, min_range_m: float | None, max_range_m: float | None, n_bands: int
                ) -> tuple[int, int]:
    """First and one-past-last row of the range window, checked to hold at least ``n_bands`` rows."""
    r = geom.range_m
    lo = 0 if min_range_m is None else int(np.searchsorted(r, min_range_m))
    hi = geom.n_bins if max_range_m is None else int(np.searchsorted(r, max_range_m))
    if hi - lo < n_bands or n_bands < 1:
        raise InputError(f"min_range_m/max_range_m: window holds {hi - lo} rows, need >= n_bands={n_bands}")
    return lo, hi


def _simulated_rows(scene: Scene, geom: SonarGeometry, config: SimulationConfig, bases: tuple[int, ...], n: int,
                    lo: int, hi: int) -> list[NDArray[np.float64]]:
    """Per base, rows ``lo:hi`` of ``n`` simulated pings of ``scene`` (seeds ``base + i``), stacked
    (:func:`iter_simulated_pings`: the scene's echo rendered once per batch of seeds)."""
    seeds = [base + i for base in bases for i in range(n)]
    rows = [np.asarray(sim.ping.image, dtype=np.float64)[lo:hi]
            for sim in iter_simulated_pings(scene, geom, config=config, seeds=seeds)]
    return [np.stack(rows[k * n:(k + 1) * n]) for k in range(len(bases))]


def compare_recording(
    real: Iterable[Ping], *, scene: str = "empty", config: SimulationConfig = SimulationConfig(),
    n_sim: int | None = None, seed: int = 0, min_range_m: float | None = None, max_range_m: float | None = None,
    n_bands: int = 10, label: str | None = None,
) -> RecordingComparison:
    """Simulate ``scene`` with the recording's geometry and compare pixel statistics.

    Parameters
    ----------
    real : iterable of Ping
        Real pings of one geometry (8-bit values k / 255).
    scene : str
        Named scene to simulate (built for the geometry: :func:`scene_from_name` with
        ``geometry=``); ``"empty"`` compares the background.
    config : SimulationConfig
        Resolved for the geometry, so the sonar profile fills the fields not set explicitly.
    n_sim : int, optional
        Number of simulated pings (default: as many as real ones).
    seed : int
        Ping ``i`` uses seed ``seed + i``; the second simulated set ``10_000 + seed + i``.
    min_range_m, max_range_m : float, optional
        Compare only the rows in this range window (e.g. the water column in front of a seabed).
    n_bands : int
        Number of equal range bands for the per-range percentiles.
    label : str, optional
        Name printed in :meth:`RecordingComparison.table`.

    Returns
    -------
    RecordingComparison

    Raises
    ------
    InputError
        If there are no pings, the pings' shapes differ, or the window holds fewer rows than bands.

    Examples
    --------
    >>> from sonarmap.io import read_pings
    >>> c = compare_recording(read_pings("../shared/data/aris/sample.aris"))  # doctest: +SKIP
    >>> round(c.kld_real_sim, 3)  # doctest: +SKIP
    0.005
    """
    pings = _one_geometry(real)
    geom = pings[0].geometry
    lo, hi = _row_window(geom, min_range_m, max_range_m, n_bands)
    n = len(pings) if n_sim is None else int(n_sim)
    built = scene_from_name(scene, seed, geometry=geom)
    real_stack = np.stack([np.asarray(p.image, dtype=np.float64)[lo:hi] for p in pings])
    sim_stack, sim2 = _simulated_rows(built, geom, config, (seed, 10_000 + seed), n, lo, hi)
    rs, ss = background_stats(real_stack), background_stats(sim_stack)
    edges = np.linspace(0, hi - lo, n_bands + 1).round().astype(np.int64)
    rp, rm = _band_stats(real_stack, edges)
    sp, sm = _band_stats(sim_stack, edges)
    r = geom.range_m
    centres = np.array([r[lo + (a + b - 1) // 2] for a, b in zip(edges[:-1], edges[1:], strict=True)])
    return RecordingComparison(
        label=label or f"{geom.name} vs simulated '{scene}'",
        scene=scene,
        geometry_name=geom.name,
        rows=(lo, hi),
        real=rs,
        sim=ss,
        kld_real_sim=histogram_kld(rs.histogram, ss.histogram),
        kld_sim_sim=histogram_kld(ss.histogram, background_stats(sim2).histogram),
        band_range_m=centres,
        real_percentiles=rp,
        sim_percentiles=sp,
        real_band_mean=rm,
        sim_band_mean=sm,
    )


#: Range in front of the seabed of the Oculus recording compared with the empty scene (m).
OCULUS_WATER_COLUMN_M = 0.45


def recording_comparisons(data_dir: str | Path = "../shared/data") -> list[RecordingComparison]:
    """The ARIS and Oculus comparisons quoted in ``docs/simulator.md``.

    ``aris/sample.aris`` (all 6 frames) against as many simulated ``empty`` pings;
    ``oculus/three_pings_8bit.raw``: the water column (range < :data:`OCULUS_WATER_COLUMN_M`,
    ring-down included) against ``empty``, and the whole image against ``seafloor``.
    """
    from sonarmap.io import read_pings

    d = Path(data_dir)
    aris = list(read_pings(d / "aris" / "sample.aris"))
    ocu = list(read_pings(d / "oculus" / "three_pings_8bit.raw"))
    return [
        compare_recording(aris, label="ARIS sample.aris (6 frames) vs simulated 'empty'"),
        compare_recording(ocu, max_range_m=OCULUS_WATER_COLUMN_M, n_bands=8,
                          label=f"Oculus three_pings_8bit.raw, water column (< {OCULUS_WATER_COLUMN_M} m) vs 'empty'"),
        compare_recording(ocu, scene="seafloor",
                          label="Oculus three_pings_8bit.raw, whole image vs simulated 'seafloor'"),
    ]


def ghost_ratios(ping: Ping, *, n_ghosts: int = 3, step: int = 8, min_peak: float = 0.15,
                 max_offset: int = 40) -> tuple[float, ...]:
    """Ghost-to-main intensity ratios at ``+-step k`` beams (k = 1..n_ghosts) of a real ping.

    For a ping showing one bright line (e.g. the DIDSON test ping 5's diagonal hull), every range
    row whose strongest beam (taper removed) reaches ``min_peak`` gives, for each offset ``d``, the
    3-row mean at the line's beam ``+ d`` over the 3-row mean at the line's beam (rows whose line
    lies within ``n_ghosts step`` beams of an edge are skipped: every offset is measured on the
    same rows).  The ratio at the ghost offsets minus the median ratio at non-ghost offsets (``4 < |d| <= max_offset``, not
    a multiple of ``step``: the background and the line's own width), averaged over both sides,
    is the ghost ratio.  Used for :data:`sonarmap.simulate.render.MEASURED_DIDSON_GHOSTS`.
    """
    img = np.asarray(ping.image, dtype=np.float64) / np.asarray(ping.geometry.taper, dtype=np.float64)[None, :]
    h, w = img.shape
    sums: dict[int, list[float]] = {d: [] for d in range(-max_offset, max_offset + 1)}
    for r in range(1, h - 1):
        j = int(img[r].argmax())
        pk = float(img[r - 1:r + 2, j].mean())
        if pk < min_peak or not n_ghosts * step <= j < w - n_ghosts * step:
            continue  # faint, or a ghost offset outside the fan
        for d in sums:
            if 0 <= j + d < w:
                sums[d].append(float(img[r - 1:r + 2, j + d].mean()) / pk)
    mean = {d: float(np.mean(v)) for d, v in sums.items() if v}
    base = float(np.median([v for d, v in mean.items() if abs(d) > 4 and d % step]))
    out = []
    for k in range(1, n_ghosts + 1):
        sides = [mean[d] - base for d in (-k * step, k * step) if d in mean]
        out.append(round(float(np.mean(sides)), 3) if sides else float("nan"))
    return tuple(out)


def main(argv: Sequence[str] | None = None) -> int:
    """Print comparisons with real recordings.

    ``[DIR]``: a directory of real DIDSON background pings (default
    ``../shared/data/didson/background``); ``FILE``: any recording :func:`sonarmap.io.read_pings`
    reads, against the simulated ``empty`` scene; ``--all [DATA_DIR]``: DIDSON, then the ARIS and
    Oculus tables of :func:`recording_comparisons`; ``--ghosts PING``: the ghost ratios of one real
    ping (:func:`ghost_ratios`).
    """
    import argparse

    from sonarmap.io.pngjson import iter_png_pings

    parser = argparse.ArgumentParser(
        prog="python -m sonarmap.simulate.compare",
        description="Compare the simulator with real recordings: a directory of DIDSON background pings (its "
                    "statistics against simulated empty pings), any recording file (against the simulated "
                    "'empty' scene of its sonar), every shared recording (--all) or one ping's ghost ratios "
                    "(--ghosts).")
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--all", metavar="DATA_DIR", nargs="?", const="../shared/data", default=None,
                      help="DIDSON background, then the ARIS and Oculus tables (default DATA_DIR ../shared/data)")
    what.add_argument("--ghosts", metavar="PING", nargs="?", const="../shared/data/didson/test/1468970074505798_raw.png",
                      default=None, help="ghost ratios at +-8, +-16, +-24 beams of one PNG ping (default: test ping 5)")
    parser.add_argument("path", nargs="?", default="../shared/data/didson/background",
                        help="directory of DIDSON background pings, or a recording file (default: %(default)s)")
    opts = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    if opts.ghosts is not None:
        from sonarmap.io.pngjson import read_png_ping

        print("ghost ratios at +-8, +-16, +-24 beams:", ghost_ratios(read_png_ping(opts.ghosts)))
        return 0
    if opts.all is not None:
        data = Path(opts.all)
        print(f"DIDSON {data / 'didson' / 'background'} (116 pings) vs 116 simulated 'empty'")
        for k, v in compare_background(iter_png_pings(data / "didson" / "background")).items():
            print(f"  {k:22s} {v:.4f}")
        for comp in recording_comparisons(data):
            print(comp.table())
        return 0
    src = Path(opts.path)
    if src.is_file():
        from sonarmap.io import read_pings

        print(compare_recording(read_pings(src), label=f"{src.name} vs simulated 'empty'").table())
        return 0
    res = compare_background(iter_png_pings(src))
    for k, v in res.items():
        print(f"{k:22s} {v:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
