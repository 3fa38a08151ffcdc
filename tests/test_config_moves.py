"""benchmarks/config_moves.py: the real-recording moves between two pipeline configurations."""

from __future__ import annotations

import numpy as np
import pytest
from benchmark_scripts import load_benchmark

from sonarmap.pipeline import PipelineConfig


@pytest.fixture(scope="module")
def moves_module():
    return load_benchmark("config_moves")


def test_the_same_configuration_moves_nothing(moves_module, test_pings) -> None:
    m = moves_module.compare(test_pings, PipelineConfig(), PipelineConfig(), "didson")
    assert m.returns_a == m.returns_b == (27, 0, 0, 0, 96, 92, 59, 88, 96, 87)
    assert m.moves_bins.size == 545 and not np.any(m.moves_bins)
    assert m.summary().startswith("| didson | 27, 0, 0, 0, 96, 92, 59, 88, 96, 87 | 0 of 545 |")


def test_the_smoothing_moves_are_measured_in_bins(moves_module, test_pings) -> None:
    """Without -> with the smoothing along the surface (541 of 545 move, the
    largest on ping 0's steep seafloor, beams 77 and 73)."""
    off = PipelineConfig().replace(edge_smooth_beams=0)
    m = moves_module.compare(test_pings, off, PipelineConfig(), "didson")
    assert m.returns_a == m.returns_b
    from sonarmap.pipeline import process_ping

    p = test_pings[0]
    res = p.geometry.range_resolution_m
    before, after = process_ping(p, off).ranges.range_m, process_ping(p, PipelineConfig()).ranges.range_m
    k = int(np.argmax(np.abs(m.moves_bins)))
    assert (m.ping[k], m.beam[k]) == (0, 77)
    assert m.moves_bins[k] == pytest.approx((after[77] - before[77]) / res)
    assert np.sum(np.abs(m.moves_bins) > 1e-6) >= 500
    assert "(ping 0, beam 77)" in m.summary()


def test_bad_arguments(moves_module, tmp_path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("edge_smooth_beams = 1\n", encoding="utf-8")
    assert moves_module.main([str(bad)]) == 1
    assert "edge_smooth_beams" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        moves_module.main(["default", "--recordings", "sonar"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        moves_module.main(["a.toml", "b.toml", "c.toml"])
    assert exc.value.code == 2


def test_one_configuration_is_compared_with_the_default(moves_module, tmp_path, capsys) -> None:
    """``config_moves.py B.toml`` is default -> B: a row per recording asked for."""
    off = tmp_path / "off.toml"
    off.write_text("edge_smooth_beams = 0\n", encoding="utf-8")
    assert moves_module.main([str(off), "--recordings", "didson"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("| recording |") and len(out) == 3
    assert out[2].startswith("| didson | 27, 0, 0, 0, 96, 92, 59, 88, 96, 87 | 541 of 545 |")
