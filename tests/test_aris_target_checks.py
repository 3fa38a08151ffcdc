"""benchmarks/aris_target_checks.py: how firmly the real ARIS target is followed, and by what."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from benchmark_scripts import load_benchmark

from sonarmap.pipeline import PipelineConfig, process_ping


@pytest.fixture(scope="module")
def checks():
    return load_benchmark("aris_target_checks")


def test_another_configuration_is_scored_against_the_defaults_curves(checks, aris_pings, tmp_path: Path) -> None:
    """``score_config`` scores exactly the configuration it is given: with the pooling aligned
    along the window's slope the frames give 272 returns (the default 278: frame 3 loses its
    faint far piece) and follow the target on as many beams (242 of 246, none in front)."""
    curves = checks.target_curves(aris_pings)
    assert curves.shape == (6, 48)
    on_d, front_d, n_d, per_d = checks.score_config(aris_pings, curves, PipelineConfig())
    cfg = PipelineConfig().replace(edge_pool_follow_slope=2.0)
    on_f, front_f, n_f, per_f = checks.score_config(aris_pings, curves, cfg)
    want = sum(int(np.isfinite(process_ping(p, cfg).ranges.range_m).sum()) for p in aris_pings)
    assert n_f == want and n_f != n_d
    assert (on_d, front_d) == (242, 0) and on_f >= 240 and front_f == 0
    assert len(per_f) == len(per_d) == 6


def test_the_command_prints_a_row_for_the_given_configuration(checks, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "follow.toml"
    cfg.write_text("[ranges]\nedge_pool_follow_slope = 2.0\n", encoding="utf-8")
    assert checks.main(["--config", str(cfg)]) == 0
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith(f"| {cfg} |")]
    assert len(rows) == 1 and rows[0].split("|")[5].strip() == "272"
