"""Table I and the background model reproduced on the shared DIDSON pings."""

from __future__ import annotations

import pytest

from sonarmap.paper import PAPER_BACKGROUND, background_counts, background_fit, table1


@pytest.mark.slow
def test_table1_within_tolerance(didson_dir):
    rows = table1(didson_dir)
    assert len(rows) == 10
    for r in rows:
        assert all(r.within_tolerance()), (r.image, r.within_tolerance())
    six = rows[6].paper
    assert six.weights[2] <= 0.002 and "no_object" in six.flags
    assert all("no_object" not in r.paper.flags for r in rows if r.image != 6)


@pytest.mark.slow
def test_background_model(didson_dir):
    f = background_fit(background_counts(didson_dir))
    pi_b, lam, kld = f.weights[1], 1 / f.params[1][0], f.kld
    assert abs(pi_b - PAPER_BACKGROUND[0]) <= 0.005
    assert abs(lam / PAPER_BACKGROUND[1] - 1) <= 0.03
    assert abs(kld / PAPER_BACKGROUND[2] - 1) <= 0.25


@pytest.mark.slow
def test_paper_command_writes_every_output(tmp_path, didson_dir, capsys):
    from PIL import Image

    from sonarmap.cli import main
    from sonarmap.paper import PAPER_OUTPUTS

    out = tmp_path / "paper"
    assert main(["paper", "--data", str(didson_dir), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert len([ln for ln in captured.out.splitlines() if ln.strip()[:1].isdigit()]) == 10  # Table I rows
    assert "fig2.png" in captured.err and "fig3.png" in captured.err
    for name in PAPER_OUTPUTS:
        assert (out / name).stat().st_size > (100 if name.endswith(".csv") else 10_000), name
    assert len((out / "table1.csv").read_text().splitlines()) == 11
    assert len((out / "background.csv").read_text().splitlines()) == 3  # header, LSQ, EM
    for name, min_size in (("fig2.png", (1200, 350)), ("fig3.png", (1200, 800))):
        with Image.open(out / name) as im:
            assert im.size[0] >= min_size[0] and im.size[1] >= min_size[1], (name, im.size)
            # a drawn figure, not a blank canvas: many distinct colours
            assert len(im.convert("RGB").getcolors(1 << 20) or ()) > 200, name


def test_fig3_profile_is_the_one_the_radial_gain_regresses(background_paths):
    """``intensity_profile`` (Fig. 3's dots) is exactly what ``estimate_radial_gain`` fits: regressing
    it again gives the same coefficients, and the fitted model follows it within its rms."""
    import numpy as np

    from sonarmap.io.pngjson import iter_png_pings
    from sonarmap.preprocess.gain import (
        estimate_radial_gain, estimate_taper, fit_range_profile, intensity_profile, radial_gain_db,
    )

    pings = list(iter_png_pings(background_paths[:20]))
    taper = estimate_taper(pings)
    gain = estimate_radial_gain(pings, taper=taper)
    level, count, geom = intensity_profile(pings, taper)
    assert geom is not None and level.shape == (geom.n_bins,)
    again = fit_range_profile(level, geom, usable=count >= 10)
    assert (again.k1, again.k2, again.k3) == pytest.approx((gain.k1, gain.k2, gain.k3), rel=1e-12)
    ok = count >= 10
    resid = 10 * np.log10(level[ok]) + radial_gain_db(geom.range_m[ok], gain)
    assert np.sqrt(np.mean((resid - resid.mean()) ** 2)) == pytest.approx(gain.rms_db, rel=1e-9)
    assert gain.rms_db < 0.5  # the channel model explains the DIDSON background's range dependence
