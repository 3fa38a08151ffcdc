"""Clipped first peaks without a Gaussian fit: the edge moved to a Gaussian echo's half-peak
crossing through the resolved rise and the clipped run (``clipped_gaussian_edges``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarmap.ranges import _kernels as rk
from sonarmap.ranges.measure import CLIP_LEVEL

NO_FITTED = np.zeros(0, dtype=np.bool_)


def _column(peak: float, width: float, centre: float = 100.0, n: int = 200) -> tuple[np.ndarray, float, int]:
    """A sampled Gaussian echo ``peak x full scale`` clipped at 1 (one beam), its crossing of half
    the clip level (linear between samples, the pipeline's plain half-of-clip edge) and its first
    clipped row."""
    r = np.arange(n, dtype=np.float64)
    col = np.minimum(peak * np.exp(-0.5 * ((r - centre) / width) ** 2), 1.0).astype(np.float32)
    c = int(np.flatnonzero(col >= CLIP_LEVEL)[0])
    i = int(np.flatnonzero(col >= 0.5)[0])
    x = i - 1 + (0.5 - col[i - 1]) / (col[i] - col[i - 1])
    return col[:, None], float(x), c


def _moved(col: np.ndarray, x: float, c: int, *, peak_bin: int | None = None, fitted: bool | None = None,
           max_over_db: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """The kernel on one echo (bins as ranges, 1 m each, a zero sigma before): the moved echoes'
    indices and new edges; its range and sigma fields checked on the way."""
    n_moved, eb, er, sg = rk.clipped_gaussian_edges(
        col, np.array([0]), np.array([x]), np.array([x]), np.zeros(1), np.array([c], dtype=np.int64),
        np.array([c if peak_bin is None else peak_bin], dtype=np.int64), CLIP_LEVEL,
        NO_FITTED if fitted is None else np.array([fitted]), fitted is not None, 10.0 ** (max_over_db / 10.0),
        np.arange(col.shape[0], dtype=np.float64), 1.0)
    moved = np.flatnonzero(eb != x)
    assert n_moved == moved.size
    assert np.array_equal(er, eb) and np.allclose(sg, (eb - x) / math.sqrt(12.0))
    return moved, eb[moved]


@pytest.mark.parametrize("peak", [2.5, 4.0, 8.0, 20.0])
@pytest.mark.parametrize("width", [3.0, 5.0])
def test_a_clipped_gaussian_echo_gets_its_half_peak_crossing_back(peak: float, width: float) -> None:
    """A Gaussian echo 2.5-20 x full scale, 3-5 bins wide: the half-of-clip edge lies 1.8-5.5 bins
    in front of the echo's half-peak crossing; moved, within 0.8 bin of it (measured at most 0.71:
    the run's middle is the peak to within half a sample, its start the full-scale crossing to
    within half a sample)."""
    col, x, c = _column(peak, width)
    truth = 100.0 - width * math.sqrt(2.0 * math.log(2.0))
    idx, new = _moved(col, x, c)
    assert truth - x > 1.5
    assert idx.tolist() == [0]
    assert abs(new[0] - truth) < 0.8, (new[0], truth, x)


def test_what_is_not_moved() -> None:
    """Nothing moves where the rise from half the clip level to full scale spans less than a bin
    (not resolved: a pulse-limited onset), where the clipped run is not the echo's first peak,
    where the Gaussian fit measured the edge, or where the echo is not clipped."""
    col, x, c = _column(4.0, 4.0)
    steep = np.zeros_like(col)
    steep[100:110] = 1.0
    steep[99] = 0.3
    for args, kw in (((steep, 99 + 0.2 / 0.7, 100), {}), ((col, x, c), {"peak_bin": c - 2}),
                     ((col, x, c), {"fitted": True}), ((col, x, -1), {})):
        idx, _ = _moved(*args, **kw)
        assert idx.size == 0, (args[1:], kw)
    idx, _ = _moved(col, x, c, fitted=False)
    assert idx.size == 1


def test_a_long_clipped_run_behind_a_short_rise_does_not_move() -> None:
    """A rise of a bin into a clipped run of 40 samples would need a Gaussian peaking ~40 dB over
    full scale: more than the bound (30 dB by default) - not one Gaussian echo - so the edge stays;
    with a bound of 60 dB it moves."""
    col = np.zeros((200, 1), dtype=np.float32)
    col[60] = 0.25
    col[61] = 0.6
    col[62:102] = 1.0
    x = 60 + (0.5 - 0.25) / (0.6 - 0.25)
    assert _moved(col, x, 62)[0].size == 0
    idx, new = _moved(col, x, 62, max_over_db=60.0)
    assert idx.size == 1 and new[0] > x


def test_the_simulated_aris_propeller_reads_closer_to_its_surface() -> None:
    """The ARIS 3000 propeller (its blades clip without enough unclipped samples for the Gaussian
    fit; one noise level, seed 0): with the move its returns' median error is 1.3 bins early
    (measured -1.29; without it -2.56), and no return moves behind the surface by more than 2 bins
    on median."""
    import sonarmap.ranges.measure as measure
    from sonarmap import preset
    from sonarmap.evaluate.segmentation import _simulate, preset_sim_configs
    from sonarmap.pipeline import PipelineConfig, process_ping

    g = preset("aris3000-128")
    sim, _ = _simulate("propeller", g, preset_sim_configs(g)[0], 0, -3.0, True)
    dr = abs(g.range_resolution_m)
    with_move = (np.asarray(process_ping(sim.ping, PipelineConfig()).ranges.range_m) - sim.surface_range_m) / dr
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(measure, "clipped_gaussian_edges", lambda echoes, *a, **k: echoes)
        without = (np.asarray(process_ping(sim.ping, PipelineConfig()).ranges.range_m) - sim.surface_range_m) / dr
    ok = np.isfinite(with_move) & np.isfinite(without)
    assert ok.sum() >= 40
    assert np.median(without[ok]) < -2.0
    assert -1.8 < np.median(with_move[ok]) < -0.8
    assert np.mean(np.abs(with_move[ok]) <= 1.0) > np.mean(np.abs(without[ok]) <= 1.0) + 0.1
