"""The import graph of ``src/sonarmap`` follows the data flow of DESIGN.md, and no package reaches
into another package's private modules or names.

Every module is parsed with :mod:`ast`; every ``import`` / ``from ... import`` counts, at module
level or inside a function (lazy imports), under ``if TYPE_CHECKING:`` too, with relative imports
resolved.  Two rules:

(a) **Flow**: a module may import only modules of its own stage or an earlier one (:data:`STAGES`).
(b) **Privacy**: across packages, no import of a private module (a dotted component starting with
    ``_``) or of a private name.  The top-level base modules in :data:`SHARED` (``_atomic``,
    ``_config``, ``_threads``, ``_files``, ``_text``, ``_histogram_kernels``, ``_precompile``) are shared
    infrastructure that every package may use; the top-level private helpers of a package
    (:data:`OWNER`) belong to that package.

Imports by string (``importlib.import_module``, forkserver preload lists) are not seen.
"""

from __future__ import annotations

import ast
import dataclasses
from collections.abc import Iterable, Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "src" / "sonarmap"

#: Stage of every package / top-level module: a module may import its own stage or lower ones.
#: Packages on the same stage (``io`` / ``store``, ``mapping`` / ``simulate``, ``plots`` /
#: ``survey``, ``report`` / ``live``, ``evaluate`` / ``paper``) may import each other.  The store
#: is on io's stage: io's zarr reader reads raw-ping stores through it, and it reads pings and
#: summarises through io (a product store's raw ping is read again from its source file); it
#: holds pings and, duck-typed, the products of later stages without importing them, so
#: ``survey`` (which fills product stores) and ``live`` come after it.
STAGES: dict[str, int] = {
    # base: the value types, the data model and shared infrastructure
    "": 0,  # sonarmap/__init__.py (imports only base modules; the rest lazily by users)
    "errors": 0, "geometry": 0, "ping": 0, "datamodel": 0, "fan": 0, "data": 0,
    "_atomic": 0, "_config": 0, "_threads": 0, "_files": 0, "_text": 0, "_histogram_kernels": 0,
    "io": 1, "store": 1,
    "preprocess": 2,
    "stats": 3,
    "classify": 4,
    "ranges": 5,
    "pipeline": 6, "config": 6, "_precompile": 6,
    "mapping": 7, "simulate": 7,
    "plots": 8, "survey": 8,
    "report": 9, "live": 9,
    "evaluate": 10, "paper": 10, "_precompile_record": 10,
    "cli": 11,
    "__main__": 12,
}

#: Top-level private modules that are shared infrastructure: importable from every package.
SHARED = frozenset({"_atomic", "_config", "_threads", "_files", "_text", "_histogram_kernels", "_precompile"})

#: Top-level private modules that belong to a package (its private helpers).
OWNER = {"_pipeline_kernels": "pipeline"}


@dataclasses.dataclass(frozen=True)
class Violation:
    module: str
    line: int
    imported: str
    rule: str

    def __str__(self) -> str:
        return f"{self.module}:{self.line}: {self.rule}: {self.imported}"


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def group_of(module: str) -> str:
    """The package a module belongs to: ``sonarmap.io.aris`` -> ``io``; ``sonarmap`` -> ``""``."""
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else ""
    return OWNER.get(top, top)


def stage_of(module: str) -> int:
    """The stage of a module (by its own top-level name: ``_pipeline_kernels`` is on pipeline's stage)."""
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else ""
    key = top if top in STAGES else OWNER.get(top, top)
    if key not in STAGES:
        raise KeyError(f"{module}: no stage for '{top}': add it to STAGES in {Path(__file__).name}")
    return STAGES[key]


def _imports(module: str, is_package: bool, tree: ast.AST) -> Iterator[tuple[str, str | None, int]]:
    """``(imported module, imported name or None, line)`` of every import of a sonarmap module."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "sonarmap" or alias.name.startswith("sonarmap."):
                    yield alias.name, None, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target == "sonarmap" or target.startswith("sonarmap."):
                for alias in node.names:
                    yield target, alias.name, node.lineno


def find_violations(sources: Iterable[tuple[str, bool, str]]) -> list[Violation]:
    """The violations of rules (a) and (b) in ``(module name, is a package __init__, source)``."""
    out: list[Violation] = []
    for module, is_package, text in sources:
        src_group, src_stage = group_of(module), stage_of(module)
        for target, name, line in _imports(module, is_package, ast.parse(text)):
            shown = f"from {target} import {name}" if name is not None else f"import {target}"
            dst_group = group_of(target)
            if dst_group == src_group:
                continue
            if stage_of(target) > src_stage:
                out.append(Violation(module, line, shown, "against the data flow"))
            dotted = target.split(".")[1:]
            private_module = any(_is_private(p) for p in dotted) and not (len(dotted) == 1 and dotted[0] in SHARED)
            if private_module or (name is not None and _is_private(name)):
                out.append(Violation(module, line, shown, "private name of another package"))
    return out


def _package_sources() -> Iterator[tuple[str, bool, str]]:
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        parts = list(rel.parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        yield ".".join(parts), is_package, path.read_text(encoding="utf-8")


def test_the_package_imports_follow_the_data_flow_and_keep_private_names_private() -> None:
    sources = list(_package_sources())
    assert len(sources) > 50  # the walk found the package
    bad = find_violations(sources)
    assert not bad, "imports breaking DESIGN.md (module:line: rule: import):\n" + "\n".join(map(str, bad))


def test_the_checker_finds_each_kind_of_bad_import() -> None:
    bad = find_violations([
        # against the flow, module level and lazily inside a function
        ("sonarmap.io.fake", False, "from sonarmap.survey import is_product_store\n"
                                    "def f():\n    from sonarmap.cli.info import describe_path\n"),
        # a private name and a private module of another package
        ("sonarmap.classify.fake", False, "from sonarmap.stats.mixture import MixtureFit, _kernel_args\n"
                                          "from sonarmap.stats import _em_kernels\n"),
        ("sonarmap.ranges", True, "def f():\n    from sonarmap.classify._kernels import first_runs\n"),
        # relative imports: against the flow from a base module, private from a sub-package
        ("sonarmap.geometry", False, "from .io import read_pings\n"),
        ("sonarmap.mapping.fake", False, "from ..io._binary import MAX_PING_BYTES\n"),
        # a package's top-level private helper, from another package
        ("sonarmap.live.fake", False, "import sonarmap.survey._warm\n"),
        # the store holds products but never imports the stage that makes them
        ("sonarmap.store.fake", False, "from sonarmap.survey import process_survey\n"),
    ])
    assert [(v.module, v.line, v.rule) for v in bad] == [
        ("sonarmap.io.fake", 1, "against the data flow"),
        ("sonarmap.io.fake", 3, "against the data flow"),
        ("sonarmap.classify.fake", 1, "private name of another package"),
        ("sonarmap.classify.fake", 2, "private name of another package"),
        ("sonarmap.ranges", 2, "private name of another package"),
        ("sonarmap.geometry", 1, "against the data flow"),
        ("sonarmap.mapping.fake", 1, "private name of another package"),
        ("sonarmap.live.fake", 1, "private name of another package"),
        ("sonarmap.store.fake", 1, "against the data flow"),
    ]
    assert str(bad[0]) == "sonarmap.io.fake:1: against the data flow: from sonarmap.survey import is_product_store"


def test_the_checker_allows_what_design_allows() -> None:
    assert find_violations([
        # the shared base modules, the root package's dunders, earlier public modules
        ("sonarmap.mapping.fake", False, "from sonarmap._atomic import atomic_path\nfrom sonarmap._files import "
                                         "read_bytes_bounded\nfrom sonarmap import __version__\n"
                                         "from sonarmap.io import read_pings\n"),
        # private modules and names inside one package, relative or absolute
        ("sonarmap.io.fake", False, "from sonarmap.io._binary import map_file\nfrom ._binary import _x\n"),
        ("sonarmap.store.writer", False, "from sonarmap.store.pings import _State\n"),
        ("sonarmap.pipeline", False, "from sonarmap._pipeline_kernels import level_counts\n"),
        # the same stage
        ("sonarmap.simulate.fake", False, "from sonarmap.mapping.poses import Pose\n"),
        ("sonarmap.cli.fake", False, "from sonarmap.cli._common import console\n"),
        # io and the store share a stage: each may import the other
        ("sonarmap.io.zarrstore", False, "from sonarmap.store import open_survey\n"),
        ("sonarmap.store.products", False, "from sonarmap.io import read_ping\n"),
    ]) == []


def test_a_module_without_a_stage_is_an_error() -> None:
    with pytest.raises(KeyError, match="add it to STAGES"):
        find_violations([("sonarmap.newstage", False, "x = 1\n")])
