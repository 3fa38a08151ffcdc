"""benchmarks/survey_figures.py: the docs/mapping.md survey tables, on surveys of a few pings."""

from __future__ import annotations

import re

import pytest
from benchmark_scripts import load_benchmark

from sonarmap.pipeline import PipelineConfig


@pytest.fixture(scope="module")
def figures():
    mod = load_benchmark("survey_figures")
    with pytest.MonkeyPatch.context() as mp:  # surveys of 3 pings
        mp.setattr(mod, "SPARSE", {"n_pings": 3})
        mp.setattr(mod, "DENSE", {"n_pings": 3, "speed_m_s": 0.25, "ping_rate_hz": 10})
        yield mod


def _numbers(row: str) -> list[float]:
    return [float(x) for x in re.findall(r"[-+]?\d+\.\d+", row)]


@pytest.mark.slow
def test_registration_rows(figures) -> None:
    rows = figures.registration_rows(PipelineConfig())
    body = [r for r in rows[2:] if "registration" not in r]
    assert len(rows) == 2 + 2 * 5
    edge = next(r for r in body if r.startswith("| hull | footprint edge |"))
    rms, p95, cov, mean_off, sd_off = _numbers(edge)[:5]
    # a few pings of the simulated hull: well inside the docs' 40-ping figures' neighbourhood
    assert 0.1 < rms < 1.0 and 0 < p95 < 0.05 and cov > 99.0 and 0.0 < mean_off < 1.0 and 0 < sd_off < 1.0
    axes = next(r for r in body if r.startswith("| hull | axes |"))
    assert _numbers(axes)[0] > rms  # the footprint edge registers closer than the axes


@pytest.mark.slow
def test_occupancy_and_range_mode_rows(figures) -> None:
    occ = figures.occupancy_rows(PipelineConfig())
    assert len(occ) == 2 + 2 * 2 * 2
    for row in occ[2:]:
        iou = _numbers("|".join(row.split("|")[3:]))  # the IoU cells, after survey and rays
        assert all(0.0 <= v <= 1.0 for v in iou) and len(iou) in (10, 6), row
    modes = figures.range_mode_rows(PipelineConfig())
    assert len(modes) == 2 + 2 * 2 * 2
    first = next(r for r in modes if "| hull, 10 cm, seed 1 | first |" in r)
    assert _numbers("|".join(first.split("|")[3:]))[0] < 0  # leading edges lie in front of the truth


def test_bad_arguments(figures, tmp_path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("edge_smooth_beams = 1\n", encoding="utf-8")
    assert figures.main(["--config", str(bad), "--parts", "registration"]) == 1
    assert "edge_smooth_beams" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        figures.main(["--parts", "maps"])
    assert exc.value.code == 2
