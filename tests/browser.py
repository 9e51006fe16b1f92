"""Debian's headless chromium driving the operator page: its DOM after the scripts ran, or
a screenshot drawn with software WebGL."""

from __future__ import annotations

import shutil
import subprocess
import tempfile

import cv2
import numpy as np
import pytest

SWIFTSHADER = ["--use-gl=swiftshader", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def chromium_dom(url: str, budget_ms: int = 8000, webgl: bool = False) -> str:
    """The page's DOM after its scripts ran, in Debian's headless chromium (with software
    WebGL, SwiftShader, where the 3D view must draw)."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.fail("chromium is not installed: scripts/install.sh installs Debian's chromium")
    with tempfile.TemporaryDirectory() as profile:
        proc = subprocess.run(
            [
                exe,
                "--headless",
                "--no-sandbox",
                *(SWIFTSHADER if webgl else ["--disable-gpu"]),
                f"--user-data-dir={profile}",
                f"--virtual-time-budget={budget_ms}",
                "--dump-dom",
                url,
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def chromium_screenshot(url: str, size: str = "900,700", budget_ms: int = 10000) -> np.ndarray:
    """The page as Debian's headless chromium draws it with software WebGL (SwiftShader):
    BGR pixels."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.fail("chromium is not installed: scripts/install.sh installs Debian's chromium")
    with tempfile.TemporaryDirectory() as tmp:
        shot = f"{tmp}/shot.png"
        proc = subprocess.run(
            [
                exe,
                "--headless",
                "--no-sandbox",
                *SWIFTSHADER,
                f"--user-data-dir={tmp}/profile",
                f"--window-size={size}",
                f"--virtual-time-budget={budget_ms}",
                f"--screenshot={shot}",
                url,
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        return cv2.imread(shot)
