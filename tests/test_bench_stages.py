"""benchmarks/bench_stages.py: the per-ping time split by stage."""

from __future__ import annotations

import types

import pytest
from benchmark_scripts import load_benchmark

import sonarmap.pipeline as pipeline


@pytest.fixture(scope="module")
def stages():
    load_benchmark("run")
    load_benchmark("bench_realtime")
    return load_benchmark("bench_stages")


def _nested(stages, monkeypatch: pytest.MonkeyPatch, outer_stage: str, inner_stage: str):
    """A fresh split on a clock only the functions advance (the test does not depend on the
    machine's load), an outer ``outer_stage`` call spending 1 s itself around an inner
    ``inner_stage`` call spending 2 s, made once; returns the split and the wrapped inner call."""
    now = [0.0]
    monkeypatch.setattr(stages, "time", types.SimpleNamespace(perf_counter=lambda: now[0]))
    split = stages._Split()

    def inner() -> None:
        now[0] += 2.0

    timed_inner = split.wrap(inner_stage, inner)

    def outer() -> None:
        now[0] += 1.0
        timed_inner()

    split.wrap(outer_stage, outer)()
    return split, timed_inner


def test_a_stage_called_inside_another_counts_as_itself_only(stages, monkeypatch: pytest.MonkeyPatch) -> None:
    """An outer stage that spends 1 s itself and calls an inner stage spending 2 s: 1 s and 2 s;
    the inner stage called again on its own adds its 2 s."""
    split, timed_inner = _nested(stages, monkeypatch, "ranges", "fit")
    assert split.total["fit"] == 2.0 and split.total["ranges"] == 1.0
    timed_inner()
    assert split.total["fit"] == 4.0 and split.total["ranges"] == 1.0
    assert split.total["classify"] == 0.0


def test_the_edge_images_own_preprocessing_counts_as_the_edge_image(stages,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The edge image pre-processes the ping again (without the deconvolution): inside it the
    pre-processing is not split off; called on its own it is the pre-processing stage."""
    split, timed_pre = _nested(stages, monkeypatch, "edge image", "normalise / pre-process")
    assert split.total["edge image"] == 3.0 and split.total["normalise / pre-process"] == 0.0
    timed_pre()
    assert split.total["edge image"] == 3.0 and split.total["normalise / pre-process"] == 2.0


def test_the_split_covers_the_pipeline_and_restores_it(stages, aris_pings) -> None:
    """On the real ARIS frames every stage but the DIDSON edge image takes time, the stages (each
    counted once: disjoint spans of the run) leave a positive rest of the total, and the pipeline's
    functions are the originals afterwards."""
    before = {name: getattr(pipeline, name) for name in ("segment", "surface_ranges", "fit_levels")}
    per, total = stages.split_ms(aris_pings, 6)
    assert set(per) == {*stages.STAGES, "rest"}
    for stage in ("normalise / pre-process", "fit", "classify", "ranges"):
        assert per[stage] > 0, stage
    assert per["edge image"] == 0.0  # (normalised pings are measured on their normalised image)
    assert 0 < per["rest"] < total
    assert sum(per.values()) == pytest.approx(total)
    assert {name: getattr(pipeline, name) for name in before} == before
