"""Shared fixtures.  Real recordings live in ``../shared/data`` beside the repository (never copied)."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# numba compiles every kernel on a fresh checkout (cached after): about half of a cold test run's
# time at LLVM's default optimisation level 3.  The tests compile at level 1 (IEEE semantics are
# the same at every level - no fast-math here - so the results are; a cold run ~15-25 % shorter, a
# warm one no slower), into a cache of their own so that the CLI and the benchmarks never load
# kernels compiled at level 1 from the cache beside the sources.  Set before numba is imported
# (it reads both once); test subprocesses inherit them.  SONARMAP_TEST_NUMBA_OPT=3 tests the
# default level (with its own cache).
_OPT = os.environ.get("SONARMAP_TEST_NUMBA_OPT", "1")
os.environ.setdefault("NUMBA_OPT", _OPT)
os.environ.setdefault("NUMBA_CACHE_DIR", str(REPO / ".pytest_cache" / f"numba-O{os.environ['NUMBA_OPT']}"))
# the command line's helper processes for a cold cache (sonarmap._precompile.compile_with_helpers)
# stay off: the test workers already keep every core busy, and the collection order below decides
# which of them compiles the pipeline
os.environ.setdefault("SONARMAP_COMPILE_HELPERS", "0")

import pytest  # noqa: E402
DATA = Path(os.environ.get("SONARMAP_DATA", REPO.parent / "shared" / "data"))


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.fail(f"shared real data missing: {path} (expected ../shared/data beside the repo)")
    return path


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``../shared/data``."""
    return _need(DATA)


@pytest.fixture(scope="session")
def didson_dir(data_dir: Path) -> Path:
    """``../shared/data/didson``."""
    return _need(data_dir / "didson")


@pytest.fixture(scope="session")
def test_ping_paths(didson_dir: Path) -> list[Path]:
    """The 10 paper test pings (images 0-9 of Table I), in time order."""
    paths = sorted((didson_dir / "test").glob("*_raw.png"))
    assert len(paths) == 10
    return paths


@pytest.fixture(scope="session")
def background_paths(didson_dir: Path) -> list[Path]:
    """The 116 open-water background pings, in time order."""
    paths = sorted((didson_dir / "background").glob("*.png"))
    assert len(paths) == 116
    return paths


@pytest.fixture(scope="session")
def test_pings(test_ping_paths: list[Path]) -> list:
    """The 10 paper test pings as :class:`sonarmap.ping.Ping`, in time order."""
    from sonarmap.io import read_pings

    return list(read_pings([str(p) for p in test_ping_paths]))


@pytest.fixture(scope="session")
def aris_pings(data_dir: Path) -> list:
    """The 6 frames of ``aris/sample.aris``."""
    from sonarmap.io import read_pings

    return list(read_pings(_need(data_dir / "aris" / "sample.aris")))


@pytest.fixture(scope="session")
def oculus_pings(data_dir: Path) -> list:
    """The 3 pings of ``oculus/three_pings_8bit.raw``."""
    from sonarmap.io import read_pings

    return list(read_pings(_need(data_dir / "oculus" / "three_pings_8bit.raw")))


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--fuzz-cases", type=int, default=200,
        help="cases per reader in tests/io/test_fuzz.py (default 200; 1000+ for the long run)",
    )


# On a cold numba cache every worker of a parallel run compiles the per-ping pipeline's kernels
# (~160 s of one core at level 1) when it first runs a ping; two workers doing it at the same time
# compile them twice for nothing.  pytest-xdist hands each worker a first chunk of consecutive tests
# (a quarter of its share) in collection order, so the collection is arranged for that: the first
# chunk starts with the pipeline's own tests (one worker compiles the pipeline), the second with
# tests of other kernels (readers, mapping, the graph-cut solvers on arbitrary unaries), which keep
# the other worker busy compiling and running those; by the time it needs the pipeline's kernels
# it finds them in the cache.  The order of tests within each group is the collection's; a run
# without workers is left as collected.
_PIPELINE_FIRST = ("tests/test_pipeline.py", "tests/test_every_sonar.py", "tests/ranges/", "tests/preprocess/")
# (in this order; ~140 s on a cold cache, about what the pipeline's compilation takes)
_OTHER_KERNELS_FIRST = ("tests/classify/test_mrf.py", "tests/classify/test_mrf_reduction.py", "tests/io/",
                        "tests/mapping/", "tests/classify/test_cfar.py", "tests/test_geometry.py", "tests/test_config.py",
                        "tests/test_fan.py", "tests/simulate/")
_OTHER_KERNELS_EXCEPT = ("tests/io/test_rosbag_types.py",)  # runs the pipeline


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    workers = int(getattr(config, "workerinput", {}).get("workercount", 0))
    if workers < 2:
        return
    chunk = max(len(items) // workers // 4, 2)  # xdist's first chunk per worker (LoadScheduling)

    def rel(item: pytest.Item) -> str:
        path = Path(str(item.path))
        return path.relative_to(REPO).as_posix() if path.is_relative_to(REPO) else path.as_posix()

    def other_rank(path: str) -> int | None:
        """The place of the path's group in _OTHER_KERNELS_FIRST (None: not in the second group)."""
        if path.startswith(_OTHER_KERNELS_EXCEPT):
            return None
        return next((k for k, prefix in enumerate(_OTHER_KERNELS_FIRST) if path.startswith(prefix)), None)

    paths = [rel(it) for it in items]
    first = [i for i, path in enumerate(paths) if path.startswith(_PIPELINE_FIRST)][:chunk]
    taken = set(first)
    ranked = [(rank, i) for i, path in enumerate(paths) if i not in taken and (rank := other_rank(path)) is not None]
    second = [i for _, i in sorted(ranked)]  # (by group, then collection order)
    taken.update(second)
    order = first + second + [i for i in range(len(items)) if i not in taken]
    items[:] = [items[i] for i in order]
