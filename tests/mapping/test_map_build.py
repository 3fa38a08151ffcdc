"""``sonarmap.mapping.map_from_pings``: the library workflow behind ``sonarmap map``."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.io import read_pings
from sonarmap.mapping import MapConfig, map_from_pings, read_point_cloud


def test_static_map_equals_the_cli_output(data_dir, tmp_path):
    from sonarmap.cli import main

    src = data_dir / "didson" / "test"
    out = tmp_path / "d.ply"
    assert main(["map", str(src), "--static", "-o", str(out), "-q"]) == 0
    res = map_from_pings(read_pings(src), MapConfig(static=True))
    cli = read_point_cloud(out)
    assert res.n_pings == 10 and res.occupancy is None and res.georef is None
    assert res.n_returns == 545 == len(res.cloud)
    np.testing.assert_allclose(res.cloud.xyz_m, cli.xyz_m, atol=1e-6)


def test_beam_axis_switch(data_dir, tmp_path):
    """``--beam-axis`` / ``footprint_edge=False`` keep every return on its beam's axis: the same
    ranges, moved off the axis by the default only across the fan (at most half a beamwidth)."""
    from sonarmap.cli import main

    src = data_dir / "oculus" / "three_pings_8bit.raw"  # its geometry gives the beamwidth
    out = tmp_path / "axis.ply"
    assert main(["map", str(src), "--static", "--beam-axis", "-o", str(out), "-q"]) == 0
    axis = map_from_pings(read_pings(src), MapConfig(static=True, footprint_edge=False)).cloud
    edge = map_from_pings(read_pings(src), MapConfig(static=True)).cloud
    np.testing.assert_allclose(axis.xyz_m, read_point_cloud(out).xyz_m, atol=1e-6)
    assert np.array_equal(axis.range_m, edge.range_m) and np.array_equal(axis.beam, edge.beam)
    rng = np.linalg.norm(edge.xyz_m, axis=1)
    np.testing.assert_allclose(rng, np.linalg.norm(axis.xyz_m, axis=1), rtol=1e-9)
    moved = np.linalg.norm(edge.xyz_m - axis.xyz_m, axis=1)
    half_width = np.radians(0.55) / 2  # the Oculus's two-way beamwidth at 2.1 MHz
    assert np.all(moved <= rng * half_width * 1.001) and (moved > 0).mean() > 0.5


def test_occupancy_map_and_the_callbacks(data_dir):
    seen, started = [], []
    res = map_from_pings(read_pings(data_dir / "oculus" / "three_pings_8bit.raw"),
                         MapConfig(static=True, grid_m=0.05, dims=2),
                         on_start=started.append, on_ping=lambda p, prod: seen.append(prod.ranges.n_returns))
    assert started == [None] and seen == [256, 256, 256]
    assert res.cloud is None and res.occupancy is not None and len(res.occupancy.to_point_cloud()) > 0
    assert res.n_returns == 768


def test_no_pose_is_an_error_before_any_processing(data_dir, monkeypatch):
    import sonarmap.pipeline as pipeline

    calls = []
    monkeypatch.setattr(pipeline, "process_ping", lambda *a, **k: calls.append(1))
    with pytest.raises(InputError, match="no pose for ping .*sample.aris#0"):
        map_from_pings(read_pings(data_dir / "aris" / "sample.aris"), MapConfig())
    assert calls == []


def test_map_config_is_validated():
    with pytest.raises(InputError, match="outside"):
        MapConfig(outside="wrap")
    with pytest.raises(InputError, match="min_confidence"):
        MapConfig(grid_m=0.1, min_confidence=0.5)
    with pytest.raises(InputError, match="no pings"):
        map_from_pings([], MapConfig(static=True))
