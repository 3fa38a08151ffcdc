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
        EM stopping rule: the fit stops when one EM step gains at most ``fit_tol`` of the
        log-likelihood (relative).  The default, 1e-11 (:func:`sonarmap.stats.mixture.fit_mixture`'s
        own), runs the fit to the likelihood maximum: parameters within ~1e-4 (relative) of it.
    fit_accelerate : bool
        Accelerate EM by SQUAREM (:func:`sonarmap.stats.mixture.fit_mixture`'s ``accelerate``; on by
        default).  The per-ping fit is the maximum-likelihood estimate, not where an EM run happened
        to stop: plain EM stopped at a 1e-6 relative gain lands 1-2 nats and 1-4 % (relative, in
        the parameters) short of the maximum on the DIDSON background pings, at points that
        differ from start to start, and the products follow that point (77 of the 275 ARIS returns
        differ between plain EM and SQUAREM stopped there).  Converged, the returns no longer depend on the stopping
        rule (1e-10 and 1e-11 give the same returns on every real recording), and it takes fewer
        EM steps on every recording but Kongsberg (per ping: DIDSON background 232 -> 126, ARIS
        116 -> 79, Oculus 55 -> 24, DIDSON test pings 24 -> 20, Kongsberg 15 -> 18).
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
    fit_tol: float = 1e-11
    fit_accelerate: bool = True
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
