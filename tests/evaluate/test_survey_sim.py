"""Simulated surveys and map accuracy against their truth (sonarmap.simulate.survey, sonarmap.evaluate.mapping)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sonarmap.mapping.occupancy import OccupancyConfig, OccupancyMap, voxel_iou
from sonarmap.mapping.poses import load_extrinsics, read_trajectory_csv, sensor_poses
from sonarmap.mapping.register import register_returns
from sonarmap.evaluate.mapping import registration_accuracy, truth_voxels
from sonarmap.pipeline import PipelineConfig
from sonarmap.simulate.survey import HullSurface, simulate_survey, surface_distance


@pytest.mark.parametrize("kind", ["hull", "seafloor"])
def test_truth_ranges_lie_on_the_surface(kind: str) -> None:
    s = simulate_survey(kind=kind, n_pings=12, render=False)
    assert np.isfinite(s.truth_range_m).mean() > 0.95  # the fan sees the surface on almost every beam
    cloud = register_returns(s.truth_range_m, s.geometry.azimuth_rad, s.poses)
    acc = registration_accuracy(s, cloud.xyz_m)
    assert acc.rms_m < 1e-9 and acc.coverage == 1.0
    # 1 cm of range noise is ~0.57 bins RMS (less after projection on the surface normal)
    noisy = s.truth_range_m + np.random.default_rng(0).normal(0, 0.01, s.truth_range_m.shape)
    acc2 = registration_accuracy(s, register_returns(noisy, s.geometry.azimuth_rad, s.poses).xyz_m)
    assert 0.3 < acc2.rms_bins < 0.6
    # points pushed 10 cm behind the surface are not "covering" it at the default tolerance
    far = register_returns(s.truth_range_m + 0.1, s.geometry.azimuth_rad, s.poses)
    assert registration_accuracy(s, far.xyz_m).coverage == 0.0


def test_surface_distance_exact_for_plane() -> None:
    hull = HullSurface(y0_m=5.0, curvature_1_m=0.0)
    pts = np.array([[0.0, 4.0, 1.0], [3.0, 5.5, -2.0]])
    assert np.allclose(surface_distance(hull, pts), [1.0, 0.5])


def test_write_and_read_back_poses(tmp_path) -> None:
    s = simulate_survey(n_pings=5, render=False)
    s.write(tmp_path)
    traj = read_trajectory_csv(tmp_path / "poses.csv")
    ext = load_extrinsics(tmp_path / "mount.json")
    sp = sensor_poses(traj, s.ping_times_ns, extrinsics=ext)
    assert np.allclose(sp.translation_m, s.poses.translation_m, atol=1e-12)
    assert np.allclose(sp.rotation, s.poses.rotation, atol=1e-12)
    # ping times fall strictly between navigation stamps (interpolation is exercised)
    assert not np.isin(s.ping_times_ns, traj.time_ns).any()
    truth = np.load(tmp_path / "truth.npz")
    assert truth["truth_range_m"].shape == (5, s.geometry.n_beams)


def test_occupancy_of_truth_ranges_matches_true_voxels() -> None:
    s = simulate_survey(n_pings=30, render=False)
    g = s.geometry
    for res in (0.05, 0.1):
        m = OccupancyMap(OccupancyConfig(resolution_m=res))
        m.integrate(s.truth_range_m, g.azimuth_rad, s.poses, min_range_m=g.min_range_m,
                    max_range_m=g.max_range_m, pd=0.95, pfa=0.02)
        iou = voxel_iou(m.occupied_cells(), truth_voxels(s, res))
        assert iou > 0.8, (res, iou)


@pytest.fixture(scope="module")
def rendered():
    from sonarmap.evaluate.mapping import evaluate_survey

    s = simulate_survey(n_pings=40, seed=1)
    return s, evaluate_survey(s)


@pytest.mark.slow
def test_rendered_survey_pings_and_poses(rendered) -> None:
    s, _ = rendered
    assert len(s.pings) == 40
    # the renderer sees the surface where the analytic truth says it is: its first structure bin
    # is within 3 bins of the zero-elevation intersection on every beam, within 1 bin on average
    # (the Gaussian elevation skirt puts it slightly nearer; a frame error would be metres off)
    first = np.stack([r.first_return_range_m for r in s.sim_truth])
    dr = s.geometry.range_resolution_m
    assert np.isfinite(first).all()
    assert np.abs(first - s.truth_range_m).max() <= 3 * dr
    assert np.abs(first - s.truth_range_m).mean() <= dr
    assert all(p.pose is not None and p.geometry == s.geometry for p in s.pings)
    assert [p.time_ns for p in s.pings] == s.ping_times_ns.tolist()


@pytest.mark.slow
def test_acceptance_registration_within_2_bins_and_coverage(rendered) -> None:
    """Issue #6: the default pipeline's registered points lie within 2 range bins RMS of the true
    hull and cover >= 90 % of the visible surface; the ranges issue's target is 0.6 bins RMS
    (measured at the footprint edge: 0.35 bins, 100 %; on the beams' axes 0.53 bins)."""
    _, ev = rendered
    assert ev.accuracy.rms_bins <= 0.6, ev.accuracy
    assert ev.accuracy.coverage >= 0.99, ev.accuracy


@pytest.mark.slow
def test_acceptance_registration_seafloor() -> None:
    """The rippled seafloor is covered where its pooled band breaks into short pieces (band
    continuation; measured 99.9 % - 91.8 % without it, ``pool_link_beams = 0``), within the
    ranges issue's 0.6 bins RMS (measured at the footprint edge: 0.45 bins; on the beams' axes
    0.65)."""
    from sonarmap.evaluate.mapping import evaluate_survey

    s = simulate_survey(n_pings=24, seed=2, kind="seafloor")
    ev = evaluate_survey(s, resolutions_m=(0.1,))
    assert ev.accuracy.rms_bins <= 0.6, ev.accuracy
    assert ev.accuracy.coverage >= 0.99, ev.accuracy


def test_dropouts_are_seeded_and_validated() -> None:
    from sonarmap.errors import InputError
    from sonarmap.simulate.survey import SurveyConfig, dropout_losses_db

    cfg = SurveyConfig(n_pings=2000, dropout_fraction=0.3, dropout_db=(6.0, 15.0), seed=3)
    loss = dropout_losses_db(cfg)
    assert abs((loss > 0).mean() - 0.3) < 0.04
    assert loss[loss > 0].min() >= 6.0 and loss.max() <= 15.0
    assert np.array_equal(loss, dropout_losses_db(cfg))  # deterministic
    assert not dropout_losses_db(SurveyConfig(n_pings=50)).any()
    with pytest.raises(InputError, match="dropout_fraction"):
        SurveyConfig(dropout_fraction=1.5)
    with pytest.raises(InputError, match="dropout_db"):
        SurveyConfig(dropout_db=(10.0, 5.0))


def test_range_measurement_pd_sees_dropped_pings() -> None:
    """An attenuated ping's detections are all rejected by the range rules: its pixel-level pD
    can still look healthy, but the range-measurement pD (what the map uses) is 0."""
    from sonarmap.pipeline import process_ping

    clean = simulate_survey(kind="seafloor", n_pings=2, seed=1)
    dropped = simulate_survey(kind="seafloor", n_pings=2, seed=1, dropout_fraction=1.0, dropout_db=(9.0, 9.0))
    for p in clean.pings:
        pr = process_ping(p)
        assert pr.ranges.n_returns >= 90 and pr.pd_range >= 0.9 * pr.pd > 0.8
    for p in dropped.pings:
        pr = process_ping(p)
        assert pr.ranges.n_returns == 0 and pr.pd_range == 0.0
    assert np.isnan(process_ping(clean.pings[0], PipelineConfig().replace(method="cfar-ca")).pd_range)


@pytest.mark.slow
def test_evaluate_survey_rejects_unknown_models(rendered) -> None:
    from sonarmap.errors import InputError
    from sonarmap.evaluate.mapping import evaluate_survey

    s, _ = rendered
    with pytest.raises(InputError, match="models"):
        evaluate_survey(s, models=("pd/pfa", "bayes"))


def _dense(kind: str):
    """A dense survey (0.25 m/s at 10 Hz: 2.5 cm between pings, each 5 cm cell seen by 2-4 pings)
    with 30 % of the pings attenuated 6-15 dB (aeration), evaluated with every sensor model for
    rays in the imaging plane and for three rays over the vertical aperture."""
    from sonarmap.evaluate.mapping import SURVEY_MODELS, evaluate_survey
    from sonarmap.pipeline import process_ping

    s = simulate_survey(kind=kind, n_pings=80, seed=1, speed_m_s=0.25, ping_rate_hz=10, dropout_fraction=0.3)
    products = [process_ping(p) for p in s.pings]
    fixed = ("fixed 0.8/0.3", "fixed 0.8/0.3, OctoMap clamps")
    return (evaluate_survey(s, products=products, models=SURVEY_MODELS),
            evaluate_survey(s, products=products, models=("pd/pfa", *fixed), n_elevation=3))


@pytest.fixture(scope="module")
def dense_hull():
    return _dense("hull")


@pytest.fixture(scope="module")
def dense_seafloor():
    return _dense("seafloor")


def _assert_pd_pfa_wins(evaluations, margin: float) -> None:
    ev, ev3 = evaluations
    assert ev.accuracy.rms_bins <= 2.0 and ev.accuracy.coverage >= 0.9, ev.accuracy
    for res in (0.05, 0.1):
        for fixed in ("fixed 0.8/0.3", "fixed 0.8/0.3, OctoMap clamps"):
            assert ev.iou[(res, "pd/pfa")] > ev.iou[(res, fixed)] + margin, ev.iou
            assert ev3.iou[(res, "pd/pfa")] > ev3.iou[(res, fixed)], ev3.iou
        # the range-measurement pD is what makes the map robust to dropped pings
        assert ev.iou[(res, "pd/pfa")] > ev.iou[(res, "pd/pfa per pixel")] + margin, ev.iou


@pytest.mark.slow
def test_acceptance_pd_pfa_occupancy_beats_fixed_constants_hull(dense_hull) -> None:
    """Hull, 30 % dropouts: each ping's pD/pFA (with per-return sigma and p_detect) beats fixed
    0.8/0.3 (with our clamps or OctoMap's) at both resolutions: measured 0.591 vs 0.577 / 0.577 at
    0.05 m, 0.690 vs 0.681 / 0.681 at 0.10 m; per-pixel pD 0.545 / 0.651 (docs/mapping.md).
    Three rays: 0.626 vs 0.598, 0.691 vs 0.674."""
    _assert_pd_pfa_wins(dense_hull, 0.005)


@pytest.mark.slow
def test_acceptance_pd_pfa_occupancy_beats_fixed_constants_seafloor(dense_seafloor) -> None:
    """Seafloor, 30 % dropouts: measured 0.644 vs 0.616 / 0.616 at 0.05 m, 0.884 vs 0.872 / 0.873
    at 0.10 m; per-pixel pD 0.548 / 0.818 (docs/mapping.md).  Three rays: 0.724 vs 0.689, 0.896
    vs 0.888."""
    _assert_pd_pfa_wins(dense_seafloor, 0.003)
