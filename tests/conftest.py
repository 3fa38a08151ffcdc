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
