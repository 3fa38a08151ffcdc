"""Headless Chromium for the tests that render HTML (the report, the demo's index page).

Chromium is a system package: ``.ci/run`` installs it; the tests never install anything.  Without
it the rendering tests skip locally and fail under CI (``CI`` set), so CI cannot pass silently
without having rendered a page.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str | None:
    """Path of a Chromium binary on ``PATH`` (None when there is none)."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(html_path: Path, png_path: Path, *, width: int = 1280, height: int = 2000) -> str:
    """Render ``html_path`` in headless Chromium to ``png_path``; returns Chromium's log (stderr)."""
    exe = find_chromium()
    if exe is None:
        msg = "chromium not found on PATH (install the system package; .ci/run does)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    profile = png_path.parent / "chromium-profile"
    cmd = [
        exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        f"--user-data-dir={profile}", f"--screenshot={png_path}", f"--window-size={width},{height}",
        "--enable-logging=stderr", "--v=0", html_path.resolve().as_uri(),
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert png_path.exists(), f"chromium wrote no screenshot (exit {r.returncode}): {r.stderr[-2000:]}"
    return r.stderr


def page_errors(log: str) -> list[str]:
    """Console messages and uncaught exceptions in a Chromium log (the page has no scripts)."""
    return [ln for ln in log.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]
