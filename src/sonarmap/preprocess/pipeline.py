"""Composable per-ping pre-processing (paper sections III-IV, eq. 2-7).

Steps, each optional, in this order (``taper_order`` places the taper before or after step 1):

0. ``taper``       - with ``taper_order="before-deconvolution"`` (the default): division of each
   beam by the taper ``k(theta)`` (eq. 5), the geometry's taper or ``taper_values``.  The taper is
   a per-beam *receive* gain applied after the beam pattern (``y_j = k_j sum_m h_m x_{j-m}``, also
   how :mod:`sonarmap.simulate` renders), so it has to be undone before the beam pattern is.
1. ``deconvolve``  - Wiener deconvolution of the beam pattern along the beams (eq. 3-4), with
   ``1/SNR = noise`` (default: the geometry's ``noise``) and the ``edge`` model; negatives are set
   to zero when ``clip_negative`` is true.
2. ``taper``       - with ``taper_order="after-deconvolution"`` (the paper's order, used by
   :meth:`PreprocessConfig.paper_table1`).
3. ``radial_gain`` - multiplication of each range bin by ``10**(k(r)/10)`` (eq. 6-7).
4. ``normalise``   - ``"none"``; ``"rescale-max"``: scale so the maximum equals the *input's*
   maximum; ``"min-max"``: subtract the minimum, then scale to the input's maximum.

Because steps 0-3 are linear and positive scalings commute with clipping, the fast path
(:func:`preprocess_image`) folds them into one cached ``(n_beams, n_beams)`` matrix (deconvolution
``M`` with the taper folded in: ``diag(1/k) M`` before, ``M diag(1/k)`` after, in the row form
``x_hat = y @ matrix``) and one per-range factor, so a ping costs one BLAS product and one
multiply.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._config import config_table
from sonarmap._files import parse_json
from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import Ping, as_image
from sonarmap.preprocess.deconvolution import _check_psf, _operator
from sonarmap.preprocess.gain import RadialGain, _check_range, _check_taper, radial_gain_factor

__all__ = ["PreprocessConfig", "preprocess", "preprocess_image", "load_config", "RECIPES", "recipe"]

Normalise = Literal["none", "rescale-max", "min-max"]
TaperOrder = Literal["before-deconvolution", "after-deconvolution"]
_EDGES = ("pad", "circular", "truncated")
_NORMALISE = ("none", "rescale-max", "min-max")
_TAPER_ORDERS = ("before-deconvolution", "after-deconvolution")


@dataclasses.dataclass(frozen=True)
class PreprocessConfig:
    """Validated pre-processing configuration (steps in the order of the module docstring).

    Parameters
    ----------
    deconvolve : bool
        Apply Wiener deconvolution (eq. 3-4) with the geometry's PSF (no-op without a PSF).
    noise : float, optional
        ``1/SNR``; ``None`` uses ``geometry.noise``.
    edge : {"pad", "circular", "truncated"}
        Edge model of :func:`sonarmap.preprocess.deconvolution.deconvolve`.
    clip_negative : bool
        Set negative intensities after deconvolution to zero.
    taper : bool
        Divide by the per-beam taper (eq. 5).
    taper_values : tuple of float, optional
        Taper to use instead of ``geometry.taper`` (e.g. from ``estimate_taper``).
    taper_order : {"before-deconvolution", "after-deconvolution"}
        Where the taper division goes.  ``"before-deconvolution"`` (default) inverts the physical
        model ``y_j = k_j (h * x)_j`` (the taper is a receive gain after the beam pattern);
        ``"after-deconvolution"`` is the paper's order (``paper_table1``).  Underscores are
        accepted for hyphens.  See ``docs/preprocessing.md``.
    radial_gain : RadialGain, optional
        Range gain of eq. 7; ``None`` skips the step.
    normalise : {"none", "rescale-max", "min-max"}
        Final intensity normalisation relative to the input ping's maximum.
    name : str
        Label recorded in the metadata (recipe name).
    """

    deconvolve: bool = True
    noise: float | None = None
    edge: Literal["pad", "circular", "truncated"] = "truncated"
    clip_negative: bool = True
    taper: bool = True
    taper_values: tuple[float, ...] | None = None
    taper_order: TaperOrder = "before-deconvolution"
    radial_gain: RadialGain | None = None
    normalise: Normalise = "none"
    name: str = "default"

    def __post_init__(self) -> None:
        for key in ("deconvolve", "clip_negative", "taper"):
            if not isinstance(getattr(self, key), bool | np.bool_):
                raise InputError(f"{key}: must be true or false, got {getattr(self, key)!r}")
            object.__setattr__(self, key, bool(getattr(self, key)))
        if self.noise is not None:
            if isinstance(self.noise, bool) or not isinstance(self.noise, int | float):
                raise InputError(f"noise: must be a number (1/SNR) or null, got {self.noise!r}")
            if not math.isfinite(self.noise) or self.noise < 0:
                raise InputError(f"noise: 1/SNR must be finite and >= 0, got {self.noise}")
            object.__setattr__(self, "noise", float(self.noise))
        if self.edge not in _EDGES:
            raise InputError(f"edge: must be one of {', '.join(_EDGES)}, got {self.edge!r}")
        order = self.taper_order.replace("_", "-") if isinstance(self.taper_order, str) else None
        if order not in _TAPER_ORDERS:
            raise InputError(
                f"taper_order: must be one of {', '.join(_TAPER_ORDERS)}, got {self.taper_order!r}"
            )
        object.__setattr__(self, "taper_order", order)
        if self.normalise not in _NORMALISE:
            raise InputError(
                f"normalise: must be one of {', '.join(_NORMALISE)}, got {self.normalise!r}"
            )
        if self.taper_values is not None:
            try:
                tv = tuple(float(v) for v in self.taper_values)
            except (TypeError, ValueError):
                raise InputError("taper_values: must be a list of numbers") from None
            if not tv or any(not math.isfinite(v) or v <= 0 for v in tv):
                raise InputError("taper_values: must be a non-empty list of positive numbers")
            object.__setattr__(self, "taper_values", tv)
        if self.radial_gain is not None and not isinstance(self.radial_gain, RadialGain):
            if isinstance(self.radial_gain, dict):
                object.__setattr__(self, "radial_gain", RadialGain.from_dict(self.radial_gain))
            else:
                raise InputError(
                    f"radial_gain: expected RadialGain or a table {{k1, k2, k3}}, got "
                    f"{type(self.radial_gain).__name__}"
                )
        if not isinstance(self.name, str):
            raise InputError(f"name: must be a string, got {self.name!r}")

    # ------------------------------------------------------------------ recipes
    @classmethod
    def paper_background(cls) -> PreprocessConfig:
        """The recipe that reproduces the paper's background statistics (eq. 19, Fig. 5).

        Wiener deconvolution with the per-ping ``1/SNR`` (0.01 in the DIDSON files), *circular*
        along the beams as in the authors' code, negatives clipped, rescaled to the input's maximum;
        no taper or range correction.  On the 116 background pings this gives a non-zero fraction
        of 0.311 (paper: pi_B = 0.312).  ``taper_order`` is the paper's (after deconvolution), so
        ``.replace(taper=True)`` (``sonarmap.paper.background_config``) divides after deconvolving.
        """
        return cls(deconvolve=True, noise=None, edge="circular", clip_negative=True, taper=False,
                   taper_order="after-deconvolution", radial_gain=None, normalise="rescale-max",
                   name="paper-background")

    @classmethod
    def paper_table1(cls) -> PreprocessConfig:
        """The recipe of the paper's Table I / Fig. 7 pre-processing.

        Per-ping PSF with ``1/SNR = 0.001`` (circular, negatives clipped, as the authors'
        ``deconvolve``), division by the per-ping taper *after* the deconvolution (the paper's
        order), then subtraction of the minimum and rescaling to the input's maximum; no radial
        gain.
        """
        return cls(deconvolve=True, noise=1e-3, edge="circular", clip_negative=True, taper=True,
                   taper_order="after-deconvolution", radial_gain=None, normalise="min-max",
                   name="paper-table1")

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON/TOML-compatible dict (``None`` values are omitted for TOML)."""
        d: dict[str, Any] = {
            "name": self.name,
            "deconvolve": self.deconvolve,
            "edge": self.edge,
            "clip_negative": self.clip_negative,
            "taper": self.taper,
            "taper_order": self.taper_order,
            "normalise": self.normalise,
        }
        if self.noise is not None:
            d["noise"] = self.noise
        if self.taper_values is not None:
            d["taper_values"] = list(self.taper_values)
        if self.radial_gain is not None:
            d["radial_gain"] = {k: v for k, v in self.radial_gain.to_dict().items() if v is not None}
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PreprocessConfig:
        """Build from a dict; unknown keys and bad values raise :class:`InputError` naming the key.

        A nested ``{"preprocess": {...}}`` table (as in a TOML file) is accepted.
        """
        kw = dict(config_table(d, cls, "preprocess config", section="preprocess", expected="a table/object"))
        if "recipe" in kw:  # pragma: no cover - reserved
            raise InputError("preprocess config: unknown key 'recipe'")
        rg = kw.get("radial_gain")
        if isinstance(rg, dict):
            kw["radial_gain"] = RadialGain.from_dict(rg)
        return cls(**kw)

    def replace(self, **changes: Any) -> PreprocessConfig:
        """Copy with fields replaced (validated)."""
        return dataclasses.replace(self, **changes)


RECIPES = ("default", "paper-table1", "paper-background")


def recipe(name: str) -> PreprocessConfig:
    """A named recipe: ``default``, ``paper-table1`` or ``paper-background``."""
    made = _RECIPES.get(name) if isinstance(name, str) else None
    if made is not None:
        return made
    if name == "default":
        made = PreprocessConfig()
    elif name == "paper-table1":
        made = PreprocessConfig.paper_table1()
    elif name == "paper-background":
        made = PreprocessConfig.paper_background()
    else:
        raise InputError(f"recipe: unknown '{name}'; choose from {', '.join(RECIPES)}")
    _RECIPES[name] = made
    return made


#: :func:`recipe` per name, built once (the configurations are immutable values).
_RECIPES: dict[str, PreprocessConfig] = {}


def load_config(path: str | os.PathLike[str]) -> PreprocessConfig:
    """Read a :class:`PreprocessConfig` from a ``.toml`` or ``.json`` file."""
    from sonarmap.errors import DataFormatError

    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise DataFormatError(f"cannot read config: {exc.strerror or exc}", p) from None
    if p.suffix.lower() == ".toml":
        import tomllib

        try:
            d = tomllib.loads(data.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise DataFormatError(f"invalid TOML: {exc}", p) from None
    else:
        d = parse_json(data, p)
    try:
        return PreprocessConfig.from_dict(d)
    except InputError as exc:
        raise InputError(f"{p}: {exc}") from None


# ---------------------------------------------------------------------- the fast path
@dataclasses.dataclass(frozen=True)
class _Plan:
    matrix: NDArray[np.float32] | None  # x_hat = y @ matrix (deconvolution and taper folded)
    row_factor: NDArray[np.float32] | None  # (n_bins, 1)
    col_factor: NDArray[np.float32] | None  # (1, n_beams): the taper without a deconvolution
    steps: tuple[str, ...]
    noise: float | None
    taper_source: str | None


@dataclasses.dataclass(frozen=True, eq=False)
class _ByContent:
    """A geometry as a cache key by its content (``SonarGeometry.key``), whatever its name.

    The plan depends only on the content; a survey's pings have one content under as many names
    (each ping's file stem), which as keys of their own would miss the cache at every ping.
    """

    geometry: SonarGeometry

    def __hash__(self) -> int:
        return hash(self.geometry.key)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _ByContent) and other.geometry.key == self.geometry.key


def _plan(geometry: SonarGeometry, config: PreprocessConfig) -> _Plan:
    """The folded pre-processing of ``geometry`` and ``config`` (cached by content; the plan of
    the previous call is reused without hashing when both are the same objects again)."""
    last = _LAST_PLAN[0]
    if last is not None and last[0] is geometry and last[1] is config:
        return last[2]
    plan = _plan_cached(_ByContent(geometry), config)
    _LAST_PLAN[0] = (geometry, config, plan)
    return plan


#: ``(geometry, config, plan)`` of the last :func:`_plan` call (a recording's pings share both).
_LAST_PLAN: list[tuple[SonarGeometry, PreprocessConfig, _Plan] | None] = [None]


@functools.lru_cache(maxsize=64)
def _plan_cached(by_content: _ByContent, config: PreprocessConfig) -> _Plan:
    geometry = by_content.geometry
    n = geometry.n_beams
    steps: list[str] = []
    M: NDArray[np.float64] | None = None
    noise: float | None = None
    if config.deconvolve and geometry.psf is not None:
        p = _check_psf(geometry.psf, n)
        assert p is not None
        noise = geometry.noise if config.noise is None else config.noise
        M = np.array(_operator(p, noise, config.edge), dtype=np.float64)
        steps.append("deconvolve")
    taper_source: str | None = None
    if config.taper:
        if config.taper_values is not None:
            t = _check_taper(config.taper_values, n)
            taper_source = "config"
        else:
            t = _check_taper(geometry.taper, n)
            taper_source = "geometry" if t is not None else None
        if t is not None:
            inv = 1.0 / t.astype(np.float64)
            # Row form x_hat = y @ M.  Taper first: (y / k) @ M = y @ (diag(1/k) M) -> scale rows
            # of M; taper after: (y @ M) / k = y @ (M diag(1/k)) -> scale columns.
            if M is None:
                M = np.diag(inv)
                steps.append("taper")
            elif config.taper_order == "before-deconvolution":
                M = M * inv[:, None]
                steps.insert(0, "taper")
            else:
                M = M * inv[None, :]
                steps.append("taper")
    row: NDArray[np.float32] | None = None
    if config.radial_gain is not None:
        r = _check_range(geometry, geometry.n_bins)
        row = np.ascontiguousarray(radial_gain_factor(r, config.radial_gain)[:, None])
        row.setflags(write=False)
        steps.append("radial_gain")
    if config.clip_negative:
        steps.append("clip_negative")
    if config.normalise != "none":
        steps.append(f"normalise:{config.normalise}")
    Mf = None
    col = None
    if M is not None and "deconvolve" not in steps:
        # a taper alone scales each column: a product with a diagonal matrix costs n_beams times
        # more and gives the same float32 values (one product per pixel, the rest exact zeros)
        col = np.ascontiguousarray(np.diag(M)[None, :], dtype=np.float32)
        col.setflags(write=False)
    elif M is not None:
        Mf = np.ascontiguousarray(M, dtype=np.float32)
        Mf.setflags(write=False)
    return _Plan(matrix=Mf, row_factor=row, col_factor=col, steps=tuple(steps), noise=noise,
                 taper_source=taper_source)


def preprocess_image(
    image: ArrayLike, geometry: SonarGeometry, config: PreprocessConfig | None = None
) -> NDArray[np.float32]:
    """Pre-process one image (the fast array path used by batch pipelines).

    Parameters
    ----------
    image : array_like, shape (n_bins, n_beams)
    geometry : SonarGeometry
        Supplies the PSF, ``noise``, taper and ranges.
    config : PreprocessConfig, optional
        Defaults to ``PreprocessConfig()``.

    Returns
    -------
    ndarray, float32, shape (n_bins, n_beams)

    Raises
    ------
    InputError
        NaN/inf or non-2-D image, bad configuration.
    GeometryError
        Image shape, PSF or taper length not matching the geometry.

    Notes
    -----
    Eq. 3-4 (deconvolution), eq. 5 (taper), eq. 6-7 (radial gain) of Teixeira et al. (2018).
    """
    cfg = PreprocessConfig() if config is None else config
    if not isinstance(geometry, SonarGeometry):
        raise InputError(f"geometry: expected SonarGeometry, got {type(geometry).__name__}")
    return _preprocessed(as_image(image, "image"), geometry, cfg, None)


def preprocess_finite(image: NDArray[np.float32], geometry: SonarGeometry, config: PreprocessConfig,
                      image_max: float) -> NDArray[np.float32]:
    """:func:`preprocess_image` of an image its caller has checked already: a non-empty 2-D
    C-contiguous float32 array of finite values whose maximum is ``image_max`` (the per-ping
    pipeline's conditioned image, whose finiteness the background estimate verified): the
    same result without a second pass for each.  Any other array goes through
    :func:`preprocess_image`."""
    if not (isinstance(image, np.ndarray) and image.dtype == np.float32 and image.ndim == 2 and image.size
            and image.flags.c_contiguous and isinstance(geometry, SonarGeometry)):
        return preprocess_image(image, geometry, config)
    return _preprocessed(image, geometry, config, image_max)


def _preprocessed(img: NDArray[np.float32], geometry: SonarGeometry, cfg: PreprocessConfig,
                  img_max: float | None) -> NDArray[np.float32]:
    """:func:`preprocess_image` of a validated image (``img_max``: its maximum, None: not known)."""
    geometry.check_image(img)
    plan = _plan(geometry, cfg)
    if plan.matrix is not None:
        out = img @ plan.matrix
    elif plan.col_factor is not None:
        out = img * plan.col_factor
    else:
        out = img.copy()
    if plan.row_factor is not None:
        out *= plan.row_factor
    if cfg.clip_negative and out.dtype == np.float32 and out.flags.c_contiguous:
        import sonarmap.preprocess._kernels as _pk

        if cfg.normalise == "none":
            _pk.clip_negative(out)  # np.maximum(out, 0.0, out=out), vectorised
            return out
        # the clipping and the normalisation below in one kernel (NaN: only clipped, numpy's way)
        if _pk.clip_rescale(out, float(img.max()) if img_max is None else img_max, cfg.normalise == "min-max"):
            return out
    elif cfg.clip_negative:
        np.maximum(out, 0.0, out=out)
    if cfg.normalise != "none":
        in_max = float(img.max()) if img_max is None else img_max
        if cfg.normalise == "min-max":
            out -= out.min()
        o_max = float(out.max())
        if o_max > 0:
            out *= np.float32(in_max / o_max)
    return out


def preprocess(ping: Ping, config: PreprocessConfig | None = None) -> Ping:
    """Pre-process a ping; returns a new :class:`Ping` with ``meta["preprocess"]`` recorded.

    ``meta["preprocess"]`` holds ``steps`` (in the order applied), ``config`` (the full
    configuration as a dict), the resolved parameters (``noise`` used, ``taper_source``),
    ``taper_order`` and ``order`` (the order of all steps for that ``taper_order``).
    The geometry is kept unchanged.
    """
    if not isinstance(ping, Ping):
        raise InputError(f"ping: expected Ping, got {type(ping).__name__}")
    cfg = PreprocessConfig() if config is None else config
    if not isinstance(cfg, PreprocessConfig):
        raise InputError(f"config: expected PreprocessConfig, got {type(cfg).__name__}")
    out = preprocess_image(ping.image, ping.geometry, cfg)
    plan = _plan(ping.geometry, cfg)
    meta = dict(ping.meta)
    record: dict[str, Any] = {
        "steps": list(plan.steps),
        "config": cfg.to_dict(),
        "noise": plan.noise,
        "taper_source": plan.taper_source,
        "taper_order": cfg.taper_order,
        "order": (
            ["taper", "deconvolve", "radial_gain", "clip_negative", "normalise"]
            if cfg.taper_order == "before-deconvolution"
            else ["deconvolve", "taper", "radial_gain", "clip_negative", "normalise"]
        ),
    }
    if "preprocess" in meta:
        prev = meta["preprocess"]
        record["previous"] = prev
    meta["preprocess"] = record
    return ping.replace(image=out, meta=meta)

