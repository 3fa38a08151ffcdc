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
