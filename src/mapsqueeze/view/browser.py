"""Headless Chromium screenshots of viewer pages (the browser test and benchmarks/view_screenshots.py).

WebGL draws headless through SwiftShader, Chromium's software renderer: `--use-gl=swiftshader` with
`--enable-unsafe-swiftshader` (without it recent Chromium refuses software WebGL). `--virtual-time-budget` lets the
page run its scripts before the shot is taken.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from mapsqueeze.errors import MapsqueezeError

BROWSER_NAMES = ("chromium", "chromium-browser", "google-chrome")
HEADLESS_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--no-first-run")


def find_chromium() -> str | None:
    """Path of a Chromium (or Chrome) executable on PATH, or None."""
    return next((path for path in map(shutil.which, BROWSER_NAMES) if path), None)


def screenshot(page: str | os.PathLike, png: str | os.PathLike, fragment: str = "", size: tuple[int, int] = (1200, 800),
               budget_ms: int = 5000, timeout_s: float = 120.0) -> Path:
    """Render the local HTML `page` (with `#fragment`, e.g. "color=error&layout=side") in headless Chromium and save
    a `size` (width, height pixels) PNG screenshot to `png`; returns its path."""
    browser = find_chromium()
    if browser is None:
        raise MapsqueezeError(f"no Chromium found (looked for {', '.join(BROWSER_NAMES)}); "
                              "install it, e.g. apt-get install chromium")
    url = Path(page).resolve().as_uri() + (f"#{fragment}" if fragment else "")
    png = Path(png).resolve()
    png.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="mapsqueeze-chromium-") as profile:
        command = [browser, *HEADLESS_FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
                   f"--virtual-time-budget={budget_ms}", f"--screenshot={png}", url]
        try:
            result = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise MapsqueezeError(f"chromium took more than {timeout_s:g} s to render {url}") from None
    if not png.is_file():
        raise MapsqueezeError(f"chromium wrote no screenshot of {url} (exit {result.returncode}): "
                              f"{result.stderr.strip()[-500:]}")
    return png
