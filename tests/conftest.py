"""Shared fixtures.  Real recordings live in ``../shared/data`` beside the repository (never copied)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
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
