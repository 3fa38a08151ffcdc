"""The configuration of the per-ping pipeline: one frozen section per stage.

:class:`PipelineConfig` holds the image conditioning options (``preprocess``, ``normalise``) and
one section per stage of :func:`sonarmap.pipeline.process_ping`:

- ``fit``: :class:`~sonarmap.stats.config.FitConfig`, the per-ping mixture fit (eq. 8-11) and
  its gates;
- ``classify``: :class:`~sonarmap.classify.config.ClassifyConfig`, the labels: MRF (eq. 17-18,
  22), local MAP, threshold, CFAR;
- ``candidates``: :class:`~sonarmap.ranges.config.CandidateConfig`, which structure pixels can
  carry a return: component rule, band pooling;
- ``ranges``: :class:`~sonarmap.ranges.config.RangeConfig`, the per-beam returns: echoes,
  leading edges, sigma, surface tracking.

In a TOML file (``--config``) each section is a table::

    [pipeline]
    normalise = "auto"

    [pipeline.classify]
    beta = 1.5

    [pipeline.ranges]
    edge_fraction = 0.3

Every option name belongs to exactly one section, so a flat table (``beta = 1.5`` at the top, the
form stores written before the sections existed hold) is read too, and
``config.replace(beta=1.5)`` replaces an option of any section by its name.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from pathlib import Path
from typing import Any

from sonarmap._config import ConfigSection, check_choice, config_error, config_table
from sonarmap.classify.config import METHODS, SOLVER_NAMES, ClassifyConfig
from sonarmap.errors import InputError
from sonarmap.ranges.config import CandidateConfig, RangeConfig
from sonarmap.stats.config import FitConfig

__all__ = ["PipelineConfig", "FitConfig", "ClassifyConfig", "CandidateConfig", "RangeConfig",
           "METHODS", "SOLVER_NAMES", "SECTIONS"]

_PREPROCESS_RECIPES = ("paper-table1", "default", "paper-background", "none")


#: The sections of :class:`PipelineConfig`, by name.
SECTIONS: dict[str, type[ConfigSection]] = {c.SECTION: c for c in (FitConfig, ClassifyConfig, CandidateConfig, RangeConfig)}

#: Each option name of a section -> its section (every name belongs to exactly one).
_OPTION_SECTION: dict[str, str] = {f.name: name for name, cls in SECTIONS.items() for f in dataclasses.fields(cls)}


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Validated configuration of :func:`sonarmap.pipeline.process_ping` (defaults = the most
    accurate pipeline, the same for every sonar).

    Parameters
    ----------
    preprocess : str or PreprocessConfig
        A recipe name (``"paper-table1"``, ``"default"``, ``"paper-background"``, ``"none"``) or an
        explicit :class:`sonarmap.preprocess.pipeline.PreprocessConfig`; applied to images that
        are not normalised (thresholded images such as DIDSON's).
    normalise : str
        ``"auto"``: images without a zero spike (ARIS, Oculus, water column) are normalised by
        their own background level (:mod:`sonarmap.preprocess.normalise`) instead of being
        pre-processed; ``"off"``: always the ``preprocess`` recipe.
    fit : FitConfig
        The mixture fit and its gates.
    classify : ClassifyConfig
        The labelling method and its parameters.
    candidates : CandidateConfig
        The component rule and band pooling.
    ranges : RangeConfig
        Echoes, leading edges, sigma and surface tracking.

    A section may be given as a dict (a TOML table).

    Examples
    --------
    >>> cfg = PipelineConfig().replace(beta=1.5, edge_fraction=0.3)
    >>> cfg.classify.beta, cfg.ranges.edge_fraction
    (1.5, 0.3)
    >>> PipelineConfig.from_dict({"classify": {"method": "map"}}).classify.method
    'map'
    """

    preprocess: Any = "paper-table1"
    normalise: str = "auto"
    fit: FitConfig = dataclasses.field(default_factory=FitConfig)
    classify: ClassifyConfig = dataclasses.field(default_factory=ClassifyConfig)
    candidates: CandidateConfig = dataclasses.field(default_factory=CandidateConfig)
    ranges: RangeConfig = dataclasses.field(default_factory=RangeConfig)

    def __post_init__(self) -> None:
        from sonarmap.preprocess.pipeline import PreprocessConfig

        where = "pipeline config: "
        pre = self.preprocess
        if isinstance(pre, dict):
            object.__setattr__(self, "preprocess", PreprocessConfig.from_dict(pre))
        elif isinstance(pre, str):
            if pre not in _PREPROCESS_RECIPES:
                raise config_error(where, "preprocess", f"must be one of {', '.join(_PREPROCESS_RECIPES)} or a table",
                                   pre)
        elif not isinstance(pre, PreprocessConfig):
            raise config_error(where, "preprocess", "must be a recipe name or a preprocess table", pre)
        check_choice(self, "normalise", ("auto", "off"), where)
        for name, cls in SECTIONS.items():
            v = getattr(self, name)
            if isinstance(v, dict):
                object.__setattr__(self, name, cls.from_dict(v))
            elif not isinstance(v, cls):
                raise config_error(where, name, f"must be a {cls.__name__} or a table", v)

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON/TOML-compatible nested dict (a table per section); :meth:`from_dict` reads it back."""
        d: dict[str, Any] = {"preprocess": self.preprocess if isinstance(self.preprocess, str)
                             else self.preprocess.to_dict(), "normalise": self.normalise}
        for name in SECTIONS:
            d[name] = getattr(self, name).to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PipelineConfig:
        """Build from a dict: section tables, and/or options by name at the top level (flat).

        A ``{"pipeline": {...}}`` table (TOML) is unwrapped.  Unknown keys, an option given both
        flat and in its section, or bad values raise :class:`InputError` naming the key.
        """
        if not isinstance(d, dict):
            raise InputError(f"pipeline config: expected a table, got {type(d).__name__}")
        if set(d) == {"pipeline"} and isinstance(d["pipeline"], dict):
            d = d["pipeline"]
        top = {"preprocess", "normalise", *SECTIONS}
        kwargs: dict[str, Any] = {}
        sections: dict[str, dict[str, Any]] = {name: {} for name in SECTIONS}
        for key, value in d.items():
            if key in SECTIONS:
                options = [(key, k, v) for k, v in config_table(value, SECTIONS[key], f"pipeline config: {key}").items()]
            elif key in _OPTION_SECTION:
                options = [(_OPTION_SECTION[key], key, value)]
            elif key in top:
                kwargs[key] = value
                continue
            else:
                valid = sorted(top | set(_OPTION_SECTION))
                raise InputError(f"pipeline config: unknown key '{key}' (valid: {', '.join(valid)})")
            for name, k, v in options:
                if k in sections[name]:
                    raise InputError(f"pipeline config: {name}.{k}: given twice (at the top and in [{name}])")
                sections[name][k] = v
        for name, table in sections.items():
            kwargs[name] = SECTIONS[name](**table)
        return cls(**kwargs)

    @classmethod
    def from_toml(cls, path: str | os.PathLike[str]) -> PipelineConfig:
        """Read a TOML file (top-level keys, a ``[pipeline]`` table and/or its section tables)."""
        p = Path(path)
        try:
            d = tomllib.loads(p.read_text(encoding="utf-8"))
        except OSError as exc:
            raise InputError(f"{p}: cannot read pipeline config ({exc.strerror or exc})") from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"{p}: invalid TOML ({exc})") from None
        try:
            return cls.from_dict(d)
        except InputError as exc:
            raise InputError(f"{p}: {exc}") from None

    def replace(self, **changes: Any) -> PipelineConfig:
        """Copy with options replaced (validated): ``preprocess``, ``normalise``, a whole section,
        or any section's option by its name (``replace(beta=1.5)`` sets ``classify.beta``)."""
        top: dict[str, Any] = {}
        per_section: dict[str, dict[str, Any]] = {}
        for key, value in changes.items():
            if key in ("preprocess", "normalise") or key in SECTIONS:
                top[key] = value
            elif key in _OPTION_SECTION:
                per_section.setdefault(_OPTION_SECTION[key], {})[key] = value
            else:
                raise InputError(f"pipeline config: unknown option '{key}'")
        for name, opts in per_section.items():
            base = top.get(name, getattr(self, name))
            if isinstance(base, dict):
                base = SECTIONS[name].from_dict(base)
            top[name] = dataclasses.replace(base, **opts)
        return dataclasses.replace(self, **top)

    def option(self, name: str) -> Any:
        """The value of an option by its name (``option("beta")`` is ``classify.beta``)."""
        if name in ("preprocess", "normalise") or name in SECTIONS:
            return getattr(self, name)
        if name not in _OPTION_SECTION:
            raise InputError(f"pipeline config: unknown option '{name}'")
        return getattr(getattr(self, _OPTION_SECTION[name]), name)

    def preprocess_config(self) -> Any:
        """The :class:`PreprocessConfig` used, or None for ``"none"``."""
        import sonarmap.preprocess.pipeline as _ppl

        if isinstance(self.preprocess, _ppl.PreprocessConfig):
            return self.preprocess
        return None if self.preprocess == "none" else _ppl.recipe(self.preprocess)
