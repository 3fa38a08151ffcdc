"""Configuration of the per-ping intensity model: the fit and its gates (a section of
:class:`sonarmap.config.PipelineConfig`)."""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

from sonarmap._config import ConfigSection, check_booleans, check_choice, check_integers, coerce_reals, config_error

__all__ = ["FitConfig"]


@dataclasses.dataclass(frozen=True)
class FitConfig(ConfigSection):
    """The per-ping intensity model (eq. 8-11) and the gates that refuse an implausible fit.

    Parameters
    ----------
    families : tuple of str
        Mixture families after the zero spike (background first).
    fit_method : str
        ``"em"`` or ``"lsq"``.
    fit_tol : float
        EM relative log-likelihood tolerance.
    fit_accelerate : bool
        Accelerate EM by SQUAREM (:func:`sonarmap.stats.mixture.fit_mixture`'s ``accelerate``).
        Off by default: at ``fit_tol = 1e-6`` plain EM stops short of the likelihood maximum
        (by up to 8e-5 relative on the ARIS sample frames), SQUAREM stops nearer to it (within
        4e-5) in 2-6x fewer EM steps, and the pipeline's products follow the fit: on the real
        recordings the same returns per ping, but 77 of 275 ARIS returns and 74 of 768 Oculus
        returns move (most by 1-30 bins; the ARIS target is followed on 237 of 246 beams against
        238, ``benchmarks/aris_target_checks.py``), one DIDSON return by one bin.
    n_levels : int
        Quantisation levels of the histogram (and of the level images the classifier labels).
    max_kld, max_object_weight, min_separation : float
        Fit gates (:func:`sonarmap.stats.gates.fit_gates`): a ping whose fit fails one yields no
        returns and carries the gate's name in its flags.  ``max_kld`` is the KL divergence
        allowed beyond what the ping's sample size explains (:func:`sonarmap.stats.gates.sampling_kld`).
    max_floor_levels : int
        The quantisation floor.  An 8-bit ping whose fit fails the KL-divergence gate is modelled
        again with the lowest ``n = 1, 2, ..`` levels of the image the classifier sees merged into
        the zero level (its level histogram shifted down by ``n`` and refitted; the image shifted
        by ``n`` levels, clamped at 0), up to this many; the first ``n`` whose fit passes every
        gate is used and reported as :attr:`PingProducts.floor_levels`.  A ping that no floor
        explains costs ``max_floor_levels`` further histogram fits.  A background whose bulk lies
        on the bottom two or three levels of the 8-bit grid (the dark water column of an Oculus
        after its automatic gain has lowered the gain for a bright hull) has no shape the grid
        resolves - its histogram falls by 5-30x per level, an exponential of less than one level -
        and the mixture's zero spike then takes it as it takes a thresholded receiver's zeros.
        Pings whose first fit passes (every DIDSON, ARIS, Oculus and Kongsberg recording) are
        unchanged.  0 = off.
    """

    SECTION: ClassVar[str] = "fit"

    families: tuple[str, ...] = ("exponential", "rayleigh")
    fit_method: str = "em"
    fit_tol: float = 1e-6
    fit_accelerate: bool = False
    n_levels: int = 256
    max_kld: float = 0.05
    max_object_weight: float = 0.5
    min_separation: float = 1.9
    max_floor_levels: int = 4

    def __post_init__(self) -> None:
        w = self._where
        coerce_reals(self, ("fit_tol", "max_kld", "max_object_weight", "min_separation"), w)
        if self.fit_tol <= 0:
            raise config_error(w, "fit_tol", "must be > 0", self.fit_tol)
        check_integers(self, (("n_levels", 2), ("max_floor_levels", 0)), w)
        check_booleans(self, ("fit_accelerate",), w)
        check_choice(self, "fit_method", ("em", "lsq"), w)
        fams = self.families
        if isinstance(fams, str) or not isinstance(fams, list | tuple) or len(fams) < 2:
            raise config_error(w, "families", "must be a list of at least two family names", fams)
        object.__setattr__(self, "families", tuple(str(f) for f in fams))

    def to_dict(self) -> dict[str, Any]:
        d = super().to_dict()
        d["families"] = list(self.families)
        return d
