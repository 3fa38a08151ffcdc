"""The pipeline configuration: one section per stage, read from nested or flat tables."""

from __future__ import annotations

import dataclasses
import json
import tomllib

import pytest

from sonarmap.config import (
    SECTIONS,
    CandidateConfig,
    ClassifyConfig,
    FitConfig,
    PipelineConfig,
    RangeConfig,
)
from sonarmap.errors import InputError


def _flat(cfg: PipelineConfig) -> dict:
    """The flat form stores hold that were written before the configuration had sections."""
    d = {"preprocess": cfg.to_dict()["preprocess"], "normalise": cfg.normalise}
    for name in SECTIONS:
        d.update(getattr(cfg, name).to_dict())
    return d


def test_every_option_belongs_to_exactly_one_section():
    names = [f.name for cls in SECTIONS.values() for f in dataclasses.fields(cls)]
    assert len(names) == len(set(names))
    assert not set(names) & {f.name for f in dataclasses.fields(PipelineConfig)}
    assert set(SECTIONS) == {"fit", "classify", "candidates", "ranges"}


def test_nested_dict_json_and_toml_round_trip():
    cfg = PipelineConfig().replace(beta=1.5, edge_fraction=0.3, max_kld=0.1, pool_factor=0.0,
                                   track={"segment_cost": 80.0}, pulse_length_m=0.01, preprocess="none")
    d = cfg.to_dict()
    assert set(d) == {"preprocess", "normalise", *SECTIONS}
    assert d["classify"]["beta"] == 1.5 and d["ranges"]["track"]["segment_cost"] == 80.0
    assert PipelineConfig.from_dict(json.loads(json.dumps(d))) == cfg
    toml = """
[pipeline]
preprocess = "none"
[pipeline.fit]
max_kld = 0.1
[pipeline.classify]
beta = 1.5
[pipeline.candidates]
pool_factor = 0.0
[pipeline.ranges]
edge_fraction = 0.3
pulse_length_m = 0.01
[pipeline.ranges.track]
segment_cost = 80
"""
    assert PipelineConfig.from_dict(tomllib.loads(toml)) == cfg


def test_flat_tables_of_older_stores_and_files_mean_the_same():
    cfg = PipelineConfig().replace(method="map", min_component_beams=8, range_mode="strongest")
    flat = _flat(cfg)
    assert "method" in flat and "classify" not in flat
    assert PipelineConfig.from_dict(flat) == cfg
    assert PipelineConfig.from_dict({"pipeline": {"beta": 1.0, "ranges": {"edge_scan": "forward"}}}) == \
        PipelineConfig(classify=ClassifyConfig(beta=1.0), ranges=RangeConfig(edge_scan="forward"))


def test_store_fingerprint_hashes_the_options_by_name():
    from sonarmap.survey.plan import _options_by_name

    cfg = PipelineConfig().replace(beta=1.5)
    assert _options_by_name(cfg.to_dict()) == _flat(cfg)


def test_replace_and_option_reach_every_section():
    cfg = PipelineConfig().replace(fit_tol=1e-5, beta=3.0, link_beams=2, edge_pool_beams=0, normalise="off")
    assert cfg.fit.fit_tol == 1e-5 and cfg.classify.beta == 3.0
    assert cfg.candidates.link_beams == 2 and cfg.ranges.edge_pool_beams == 0 and cfg.normalise == "off"
    assert cfg.option("beta") == 3.0 and cfg.option("normalise") == "off"
    assert cfg.option("fit") is cfg.fit
    # a whole section and one of its options at once: the option applies to the given section
    c2 = cfg.replace(classify={"method": "map"}, beta=0.5)
    assert c2.classify == ClassifyConfig(method="map", beta=0.5)
    assert PipelineConfig().replace(fit=FitConfig(max_kld=0.2)).fit.max_kld == 0.2
    with pytest.raises(InputError, match="unknown option 'bogus'"):
        PipelineConfig().replace(bogus=1)
    with pytest.raises(InputError, match="unknown option 'bogus'"):
        PipelineConfig().option("bogus")


@pytest.mark.parametrize("table, message", [
    ({"beta": -1}, r"pipeline config: classify\.beta: must be a finite number >= 0 \(got -1\)"),
    ({"classify": {"neighbourhood": 6}}, r"classify\.neighbourhood: must be 4 or 8"),
    ({"fit": {"families": ["exponential"]}}, r"fit\.families: must be a list of at least two"),
    ({"candidates": {"pool_mode": "always"}}, r"candidates\.pool_mode: must be 'fallback' or 'fill'"),
    ({"ranges": {"edge_fraction": 1.0}}, r"ranges\.edge_fraction: must lie in \[0, 1\)"),
    ({"ranges": {"track": {"bogus": 1}}}, r"ranges\.track: unknown key 'bogus'"),
    ({"classify": {"bogus": 1}}, r"pipeline config: classify: unknown key 'bogus' \(valid: beta, "),
    ({"bogus": 1}, r"pipeline config: unknown key 'bogus'"),
    ({"beta": 1.0, "classify": {"beta": 2.0}}, r"classify\.beta: given twice"),
    ({"classify": {"beta": 2.0}, "beta": 1.0}, r"classify\.beta: given twice"),
    ({"classify": 3}, r"pipeline config: classify: expected a table, got int"),
    ({"normalise": "sometimes"}, r"pipeline config: normalise: must be 'auto' or 'off'"),
    ({"preprocess": "sharpen"}, r"pipeline config: preprocess: must be one of paper-table1"),
    ({"classify": {"contrast": 1}}, r"classify\.contrast: must be true or false \(got 1\)"),
    ({"ranges": {"min_run": True}}, r"ranges\.min_run: must be an integer >= 1 \(got True\)"),
])
def test_bad_tables_are_refused_naming_section_and_key(table, message):
    with pytest.raises(InputError, match=message):
        PipelineConfig.from_dict(table)


def test_sections_validate_on_their_own_and_are_frozen():
    with pytest.raises(InputError, match=r"candidates\.pool_bins: must be an integer >= 1"):
        CandidateConfig(pool_bins=0)
    with pytest.raises(InputError, match=r"pipeline config: fit: must be a FitConfig or a table"):
        PipelineConfig(fit="em")  # type: ignore[arg-type]
    with pytest.raises(dataclasses.FrozenInstanceError):
        PipelineConfig().classify.beta = 1.0  # type: ignore[misc]
    assert PipelineConfig(classify={"beta": 1}).classify.beta == 1.0  # tables coerced, reals as float
    assert isinstance(PipelineConfig(classify={"beta": 1}).classify.beta, float)


def test_toml_file_errors_name_the_file(tmp_path):
    p = tmp_path / "cfg.toml"
    p.write_text("[pipeline.classify]\nbeta = -2\n")
    with pytest.raises(InputError, match=r"cfg\.toml: pipeline config: classify\.beta"):
        PipelineConfig.from_toml(p)
    p.write_text("[pipeline.ranges]\nrange_mode = 'strongest'\n")
    assert PipelineConfig.from_toml(p).ranges.range_mode == "strongest"


def test_demo_configuration_file_is_the_default_pipeline():
    from sonarmap.cli.demo import DEMO_CONFIG

    d = tomllib.loads(DEMO_CONFIG)
    assert set(d["pipeline"]) == {"fit", "classify", "candidates", "ranges"}
    assert PipelineConfig.from_dict(d) == PipelineConfig()
