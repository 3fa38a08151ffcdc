"""Compare simulated open-water pings with real background pings (histograms, zero spike, KLD).

Run ``python -m sonarmap.simulate.compare ../shared/data/didson/background`` to print the table
quoted in ``docs/simulator.md``.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from sonarmap.ping import Ping
from sonarmap.simulate.render import SimulationConfig, simulate_ping
from sonarmap.simulate.scene import empty_scene

__all__ = ["BackgroundStats", "background_stats", "histogram_kld", "compare_background", "ghost_ratios"]


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

    ``eps`` is added to both before renormalising so empty bins do not give infinities.
    """
    a = np.asarray(p, dtype=np.float64) + eps
    b = np.asarray(q, dtype=np.float64) + eps
    a /= a.sum()
    b /= b.sum()
    return float(np.sum(a * np.log(a / b)))


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


def main(argv: list[str] | None = None) -> int:
    """Print the comparison for a directory of real background pings (``--ghosts PING``: the
    ghost ratios of one real ping, see :func:`ghost_ratios`)."""
    from sonarmap.io.pngjson import iter_png_pings

    args = sys.argv[1:] if argv is None else argv
    if args and args[0] == "--ghosts":
        from sonarmap.io.pngjson import read_png_ping

        src = args[1] if len(args) > 1 else "../shared/data/didson/test/1468970074505798_raw.png"  # test ping 5
        print("ghost ratios at +-8, +-16, +-24 beams:", ghost_ratios(read_png_ping(src)))
        return 0
    src = args[0] if args else "../shared/data/didson/background"
    res = compare_background(iter_png_pings(src))
    for k, v in res.items():
        print(f"{k:22s} {v:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
