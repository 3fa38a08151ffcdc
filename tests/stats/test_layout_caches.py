"""The per-layout caches of the fit and its gates give what they replace (numpy masks), and a
fit built by ``MixtureFit._of`` equals one built by its dataclass ``__init__``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sonarmap.stats.gates import _class_members, class_separation
from sonarmap.stats.mixture import MixtureFit, _members_by_class, _object_members, fit_mixture

LAYOUTS = [
    ((0, 0, 1), ("zero", "exponential", "rayleigh")),
    ((0, 1), ("exponential", "rayleigh")),
    ((0, 0, 1, 2), ("zero", "exponential", "rayleigh", "gamma")),
    ((0, 0, 0, 1, 1), ("zero", "exponential", "gamma", "rayleigh", "rice")),
    ((0, 0), ("zero", "exponential")),
]


@pytest.mark.parametrize(("classes", "names"), LAYOUTS)
def test_members_are_those_of_the_masks(classes: tuple[int, ...], names: tuple[str, ...]) -> None:
    cls = np.asarray(classes)
    assert _object_members(classes).tolist() == list(np.flatnonzero(cls != 0))
    n_classes = int(cls.max()) + 1
    assert tuple(m.tolist() for m in _members_by_class(classes, n_classes)) == tuple(
        list(np.flatnonzero(cls == j)) for j in range(n_classes))
    bg, obj = _class_members(classes, names)
    assert bg == [i for i in range(len(names)) if classes[i] == 0 and names[i] != "zero"]
    assert obj.tolist() == list(np.flatnonzero(cls != 0))
    w = np.random.default_rng(len(classes)).random(len(classes))
    assert float(w[_object_members(classes)].sum()) == float(w[cls != 0].sum())


def test_a_fit_built_without_init_equals_the_dataclass() -> None:
    rng = np.random.default_rng(3)
    y = np.r_[np.zeros(3000), rng.exponential(0.03, 2500), rng.rayleigh(0.25, 500)]
    fit = fit_mixture(np.clip(y, 0, 1).reshape(60, 100), method="em")
    fields = {f.name: getattr(fit, f.name) for f in dataclasses.fields(MixtureFit) if f.init}
    again = MixtureFit(**fields)
    assert set(vars(again)) == set(vars(fit))
    for name in fields:
        assert getattr(again, name) is getattr(fit, name)
    assert fit.object_weight == again.object_weight
    assert class_separation(fit) == class_separation(again)
    np.testing.assert_array_equal(fit.decision_log_pmf(), again.decision_log_pmf())


def test_the_fits_own_arrays_without_a_copy() -> None:
    rng = np.random.default_rng(4)
    y = np.r_[np.zeros(3000), rng.exponential(0.03, 2500), rng.rayleigh(0.25, 500)]
    fit = fit_mixture(np.clip(y, 0, 1).reshape(60, 100), method="em")
    for name in ("class_prior", "class_log_pmf", "decision_log_pmf", "class_pmf"):
        own = getattr(fit, name)(copy=False)
        assert not own.flags.writeable and getattr(fit, name)(copy=False) is own
        mine = getattr(fit, name)()
        assert mine.flags.writeable and mine is not own and np.array_equal(mine, own)
    assert set(fit._cache) == {"component_pmfs", "class_prior", "class_log_pmf", "decision_log_pmf", "class_pmf"}
