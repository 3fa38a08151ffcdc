"""benchmarks/bench_stages.py: the per-ping time split by stage."""

from __future__ import annotations

import time

import pytest
from benchmark_scripts import load_benchmark

import sonarmap.pipeline as pipeline


@pytest.fixture(scope="module")
def stages():
    load_benchmark("run")
    load_benchmark("bench_realtime")
    return load_benchmark("bench_stages")


def test_a_stage_called_inside_another_counts_as_itself_only(stages) -> None:
    split = stages._Split()

    def inner() -> None:
        time.sleep(0.02)

    timed_inner = split.wrap("fit", inner)

    def outer() -> None:
        time.sleep(0.01)
        timed_inner()

    split.wrap("ranges", outer)()
    assert 0.019 <= split.total["fit"] < 0.03
    assert 0.009 <= split.total["ranges"] < 0.019


def test_the_split_covers_the_pipeline_and_restores_it(stages, aris_pings) -> None:
    """On the real ARIS frames every stage but the DIDSON edge image takes time, the stages and
    the rest add up to the total, and the pipeline's functions are the originals afterwards."""
    before = {name: getattr(pipeline, name) for name in ("segment", "surface_ranges", "fit_levels")}
    per, total = stages.split_ms(aris_pings, 6)
    assert set(per) == {*stages.STAGES, "rest"}
    for stage in ("normalise / pre-process", "fit", "classify", "ranges"):
        assert per[stage] > 0, stage
    assert per["edge image"] == 0.0  # (normalised pings are measured on their normalised image)
    assert sum(per.values()) == pytest.approx(total)
    assert {name: getattr(pipeline, name) for name in before} == before
