"""Per-beam range extraction: first/strongest return, consistency rules, explicit no-return."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarmap.errors import GeometryError, InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ranges import BeamRanges, extract_ranges, first_return_bins, no_returns


@pytest.fixture(scope="module")
def geom() -> SonarGeometry:
    return SonarGeometry.from_window(min_range_m=2.0, max_range_m=12.0, n_bins=100, n_beams=20, fov_rad=0.5)


def test_first_and_strongest_in_metres(geom):
    mask = np.zeros(geom.shape, bool)
    img = np.zeros(geom.shape, np.float32)
    mask[40:44, :] = True
    img[40:44, :] = 0.5
    img[42, :] = 0.9
    r = extract_ranges(mask, img, geom)
    assert r.n_returns == 20
    np.testing.assert_array_equal(r.bin, 40)
    np.testing.assert_allclose(r.range_m, 2.0 + 40 * 0.1)
    np.testing.assert_allclose(r.intensity, 0.5)
    np.testing.assert_allclose(r.confidence, 1.0)
    s = extract_ranges(mask, img, geom, mode="strongest")
    np.testing.assert_array_equal(s.bin, 42)
    np.testing.assert_allclose(s.azimuth_rad, geom.azimuth_rad)


def test_no_return_is_explicit(geom):
    r = extract_ranges(np.zeros(geom.shape, np.uint8), np.zeros(geom.shape), geom)
    assert r.n_returns == 0
    assert (r.bin == -1).all() and np.isnan(r.range_m).all() and np.isnan(r.intensity).all()
    assert (r.confidence == 0).all()
    n = no_returns(geom, source="x")
    assert n.n_returns == 0 and n.source == "x"


def test_isolated_return_rejected_and_min_run(geom):
    lab = np.zeros(geom.shape, np.uint8)
    lab[50, 3:15] = 1       # a surface over 12 beams
    lab[10, 18] = 1         # an isolated speckle on beam 18
    lab[20, 5] = 1          # a lone pixel in front of the surface on beam 5
    r = extract_ranges(lab, np.ones(geom.shape), geom, min_run=1)
    assert r.bin[18] == -1  # no neighbour within max_jump_bins -> rejected
    assert r.bin[5] == 50   # the lone pixel in front has no support: falls back to the surface
    r2 = extract_ranges(lab, np.ones(geom.shape), geom, min_run=1, reject_isolated=False)
    assert r2.bin[18] == 10
    lab[21, 5] = 1
    lab[20:22, 5] = 1
    thick = lab.copy()
    thick[51, 3:15] = 1
    r3 = extract_ranges(thick, np.ones(geom.shape), geom, min_run=2, reject_isolated=False)
    assert r3.bin[5] == 20  # a 2-bin run in front is a return
    lab2 = np.zeros(geom.shape, np.uint8)
    lab2[50:52, 3:15] = 1
    lab2[20, 5] = 1
    r4 = extract_ranges(lab2, np.ones(geom.shape), geom, min_run=2)
    assert r4.bin[5] == 50  # the single-bin speckle is skipped


def test_component_and_segment_rules(geom):
    lab = np.zeros(geom.shape, bool)
    lab[60:62, 0:15] = True       # wide surface
    lab[30:32, 16:20] = True      # narrow blob (fish) on beams 16-19
    r = extract_ranges(lab, np.ones(geom.shape), geom, min_component_beams=6)
    assert (r.bin[:15] == 60).all() and (r.bin[16:] == -1).all()
    r = extract_ranges(lab, np.ones(geom.shape), geom, min_segment_beams=6)
    assert (r.bin[16:] == -1).all()
    steep = np.zeros(geom.shape, bool)
    for j in range(4):
        steep[10 + 20 * j:30 + 20 * j, j] = True   # a steep surface: 4 beams, 80 bins
    r = extract_ranges(steep, np.ones(geom.shape), geom, min_component_beams=6, min_component_bins=40,
                       max_jump_bins=20)
    assert r.n_returns == 4


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["first", "strongest"]), st.booleans())
def test_returns_are_structure_pixels(seed, mode, reject):
    geom = SonarGeometry.from_window(min_range_m=1.0, max_range_m=5.0, n_bins=30, n_beams=12, fov_rad=0.4)
    rng = np.random.default_rng(seed)
    mask = rng.random(geom.shape) < 0.1
    img = rng.random(geom.shape).astype(np.float32)
    r = extract_ranges(mask, img, geom, mode=mode, reject_isolated=reject)
    v = r.valid
    cols = np.flatnonzero(v)
    assert mask[r.bin[v], cols].all()
    assert np.array_equal(v, np.isfinite(r.range_m))
    assert ((r.confidence >= 0) & (r.confidence <= 1)).all()
    if mode == "first" and not reject:
        np.testing.assert_array_equal(r.bin, first_return_bins(mask))
    if mode == "strongest":
        for j in cols:
            assert img[r.bin[j], j] == img[mask[:, j], j].max()


def test_bad_inputs(geom):
    with pytest.raises(GeometryError, match="labels_or_mask"):
        extract_ranges(np.zeros((3, 3)), np.zeros(geom.shape), geom)
    with pytest.raises(InputError, match="mode"):
        extract_ranges(np.zeros(geom.shape), np.zeros(geom.shape), geom, mode="last")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="bin/range_m"):
        BeamRanges(range_m=np.array([1.0]), bin=np.array([-1]), intensity=np.zeros(1, np.float32),
                   confidence=np.zeros(1, np.float32), azimuth_rad=np.zeros(1))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 10), st.integers(0, 15))
def test_wide_components_matches_scipy_labelling(seed, min_beams, min_bins):
    from scipy import ndimage

    from sonarmap.ranges import wide_components

    rng = np.random.default_rng(seed)
    m = rng.random((40, 30)) < rng.uniform(0.05, 0.5)
    lab, n = ndimage.label(m, structure=np.ones((3, 3)))
    keep = np.zeros(n + 1, bool)
    for k, sl in enumerate(ndimage.find_objects(lab), 1):
        keep[k] = sl[1].stop - sl[1].start >= min_beams or (min_bins > 0 and sl[0].stop - sl[0].start >= min_bins)
    got = wide_components(m, min_beams, min_bins=min_bins if min_bins > 0 else None)
    np.testing.assert_array_equal(got, keep[lab] & m)


def test_accepted_pixels_bypass_component_rule_and_refinement(geom):
    img = np.zeros((100, 20), np.float32)
    mask = np.zeros((100, 20), bool)
    acc = np.zeros((100, 20), bool)
    acc[50, :] = True                      # one pixel per beam: dropped by the component rule alone
    img[45:51, :] = 1.0                    # a bright leading edge that rule 4 would climb
    kw = dict(min_component_beams=30, min_component_bins=30, refine_bins=8, edge_level=0.5)
    assert extract_ranges(mask | acc, img, geom, **kw).n_returns == 0
    r = extract_ranges(mask, img, geom, accepted=acc, **kw)
    assert r.n_returns == 20 and (r.bin == 50).all()
    with pytest.raises((InputError, GeometryError)):
        extract_ranges(mask, img, geom, accepted=acc[:, :5])


def test_fused_rule0_equals_wide_then_linked_components():
    """The one-kernel rule 0 equals wide_components followed by _link_components."""
    from sonarmap.ranges import _link_components, rule0, wide_components

    rng = np.random.default_rng(3)
    for t in range(400):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 40))
        m = rng.random((h, w)) < rng.uniform(0.02, 0.5)
        mb = int(rng.integers(1, 10))
        mn = None if t % 2 else int(rng.integers(1, 10))
        gap = int(rng.integers(0, 6))
        ref = wide_components(m, mb, min_bins=mn)
        if gap > 0:
            ref = _link_components(m, ref, gap)
        assert np.array_equal(rule0(m, mb, mn, gap), ref)


def test_component_rule_with_extent_equals_rule0_then_drop_small_components():
    """component_rule's one-pass extent rule equals rule 0 followed by a per-component (scipy) extent
    test, with and without rule 0, on random masks of a fan."""
    from extent_reference import extent_reference

    from sonarmap.ranges import component_rule, rule0

    g = SonarGeometry(range_m=0.5 + 0.02 * np.arange(60), azimuth_rad=np.deg2rad(np.linspace(-20, 20, 30)))
    rng = np.random.default_rng(5)
    for t in range(200):
        m = rng.random(g.shape) < rng.uniform(0.02, 0.4)
        mb, mn, gap, px = int(rng.integers(1, 12)), int(rng.integers(0, 12)), int(rng.integers(0, 5)), int(t % 3) * 10
        e = float(rng.choice([0.0, 0.05, 0.1, 0.3]))
        ruled = rule0(m, mb, mn, gap, px) if mb > 1 or px > 0 else m
        ref = extent_reference(ruled, g, e) if e > 0 else ruled
        assert np.array_equal(component_rule(m, mb, mn, gap, px, geometry=g, min_extent_m=e), ref)


def test_with_p_detect_is_replace_without_rechecking(geom):
    import dataclasses

    mask = np.zeros(geom.shape, bool)
    mask[40:44, 5:15] = True
    r = extract_ranges(mask, mask.astype(np.float32), geom)
    p = np.linspace(0, 1, geom.n_beams)
    new = r.with_p_detect(p)
    ref = dataclasses.replace(r, p_detect=p)
    assert new.p_detect.dtype == np.float32 and new is not r
    for f in dataclasses.fields(BeamRanges):
        a, b = getattr(new, f.name), getattr(ref, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b
    assert np.isnan(r.p_detect).all()  # the original is untouched
    with pytest.raises(InputError, match="p_detect"):
        r.with_p_detect(p[:-1])


@pytest.mark.parametrize("seed", range(12))
def test_first_clipped_rows_by_rows_equals_the_column_walk(seed: int) -> None:
    """first_clipped_rows gives the first row reaching the level in each interval, whether it lists
    the clipped samples from a pass along the rows (intervals covering much of their span) or walks
    each interval down its column (few, short intervals)."""
    from sonarmap.ranges._kernels import first_clipped_rows

    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(1, 60)), int(rng.integers(1, 40))
    img = rng.random((n, m)).astype(np.float32 if seed % 2 else np.float64)
    if seed % 3 == 0:
        img[rng.random((n, m)) < 0.1] = np.nan
    k = int(rng.integers(0, 3 * m)) if seed % 4 else 2
    cols = rng.integers(0, m, k).astype(np.int64)
    lo = rng.integers(0, n + 1, k).astype(np.int64)
    hi = np.minimum(lo + rng.integers(-2, n if seed % 4 else 3, k), n).astype(np.int64)
    level = float(rng.choice([0.5, 0.9, 0.99, 2.0]))
    want = [next((i for i in range(a, b) if img[i, j] >= level), -1) for j, a, b in zip(cols, lo, hi)]
    assert first_clipped_rows(img, cols, lo, hi, level).tolist() == want


def test_full_scale_mask_agrees_with_the_kernels_at_the_level():
    """The pooled profile's clip mask and the kernels' first clipped rows count the same samples as
    clipped, also at the float32 values either side of the level (compared in float64)."""
    from sonarmap.ranges._kernels import first_clipped_rows
    from sonarmap.ranges.measure import CLIP_LEVEL, full_scale_mask

    f = np.float32(CLIP_LEVEL)
    vals = np.array([np.nextafter(f, np.float32(0)), f, np.nextafter(f, np.float32(2)), 1.0, 0.5], np.float32)
    img = np.tile(vals[:, None], (1, 3))
    mask = full_scale_mask(img)
    rows = [first_clipped_rows(img, np.array([0]), np.array([k]), np.array([k + 1]), CLIP_LEVEL)[0]
            for k in range(vals.size)]
    assert mask[:, 0].tolist() == [r >= 0 for r in rows]
    assert mask[:, 0].tolist() == (vals.astype(np.float64) >= CLIP_LEVEL).tolist()
    u8 = np.array([[254, 255]], np.uint8) / np.float64(255.0)
    assert full_scale_mask(u8).tolist() == [[False, True]]
