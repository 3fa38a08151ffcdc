"""Configuration of the classification stage (a section of :class:`sonarmap.config.PipelineConfig`)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from sonarmap._config import ConfigSection, check_booleans, check_choice, check_integers, coerce_reals, config_error

__all__ = ["ClassifyConfig", "METHODS", "SOLVER_NAMES"]

#: The labelling methods of the pipeline.
METHODS = ("mrf", "map", "threshold", "cfar-ca", "cfar-so", "cfar-go", "cfar-os")
#: The MRF solvers.
SOLVER_NAMES = ("graphcut", "icm", "anneal", "expansion")


@dataclasses.dataclass(frozen=True)
class ClassifyConfig(ConfigSection):
    """Per-pixel labels: the MRF (eq. 17-18, 22; the default), local MAP (eq. 12-13), a fixed
    threshold (eq. 14) or the CFAR baselines.

    Parameters
    ----------
    method : str
        ``"mrf"``, ``"map"`` (local MAP), ``"threshold"`` (fixed), or ``"cfar-ca|so|go|os"``.
    solver : str
        MRF solver: ``"graphcut"`` (exact; alpha-expansion for > 2 classes), ``"icm"``,
        ``"anneal"`` (the paper's), ``"expansion"``.
    beta : float
        Potts weight of eq. 22.
    neighbourhood : int
        4 or 8.
    contrast : bool
        Contrast-sensitive pairwise weights.
    range_weight : float
        Factor on the Potts weight along range (anisotropic prior): surfaces are thin in range and
        long across beams; 0.25 keeps 1-3-bin surfaces intact while smoothing across beams.
    object_prior_min : float
        Lower bound on each object class's prior in the MRF unary.  The fitted object weight of
        a ping with a thin, faint surface can be ~0.001 (Table I image 6), which makes the
        posterior reject the surface however clearly it stands out; the Potts prior (not the
        class prior) is then what should suppress speckle.
    speckle_eps : float
        Speckle-robust object likelihood ``(1 - eps) p(y|object) + eps p(y|background)`` in the
        MRF unary (0: the paper's model, where a zero pixel can never be structure).
    grow_prior_min, grow_beta : float
        Hysteresis growth (MRF only; off when ``grow_prior_min`` is 0): a second, more permissive
        cut (object prior raised to ``grow_prior_min``, Potts weight ``grow_beta``) labels faint
        structure, which is kept only where it is 8-connected to the first cut's structure -
        faint low-incidence continuations of a surface are recovered, isolated faint blobs are not.
    threshold : float
        Intensity threshold of ``method="threshold"`` (eq. 14), on the pre-processed image.
    cfar_train, cfar_guard : int
        CFAR training / guard cells along range (total, even); sonar-SLAM: 40 / 10.
    cfar_pfa : float
        CFAR design false-alarm probability (sonar-SLAM: 0.1).
    cfar_two_d : bool
        2-D CFAR window (range x beams).
    """

    SECTION: ClassVar[str] = "classify"

    method: str = "mrf"
    solver: str = "graphcut"
    beta: float = 2.0
    neighbourhood: int = 4
    contrast: bool = False
    range_weight: float = 0.25
    object_prior_min: float = 0.2
    speckle_eps: float = 0.0
    grow_prior_min: float = 0.0
    grow_beta: float = 1.0
    threshold: float = 0.3
    cfar_train: int = 40
    cfar_guard: int = 10
    cfar_pfa: float = 0.1
    cfar_two_d: bool = False

    def __post_init__(self) -> None:
        w = self._where
        check_choice(self, "method", METHODS, w)
        check_choice(self, "solver", SOLVER_NAMES, w)
        coerce_reals(self, ("threshold", "cfar_pfa"), w)
        coerce_reals(self, ("beta", "grow_beta"), w, minimum=0)
        coerce_reals(self, ("object_prior_min", "grow_prior_min", "speckle_eps", "range_weight"), w)
        for key in ("object_prior_min", "grow_prior_min", "speckle_eps"):
            if not 0 <= getattr(self, key) < 0.5:
                raise config_error(w, key, "must lie in [0, 0.5)", getattr(self, key))
        if not 0 <= self.range_weight <= 1:
            raise config_error(w, "range_weight", "must lie in [0, 1]", self.range_weight)
        if not 0 < self.cfar_pfa < 1:
            raise config_error(w, "cfar_pfa", "must lie in (0, 1)", self.cfar_pfa)
        check_integers(self, (("neighbourhood", 4), ("cfar_train", 2), ("cfar_guard", 0)), w)
        if self.neighbourhood not in (4, 8):
            raise config_error(w, "neighbourhood", "must be 4 or 8", self.neighbourhood)
        for key in ("cfar_train", "cfar_guard"):
            if getattr(self, key) % 2:
                raise config_error(w, key, "must be even", getattr(self, key))
        check_booleans(self, ("contrast", "cfar_two_d"), w)
