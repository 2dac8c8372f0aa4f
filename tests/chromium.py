"""The headless Chromium that the console's tests and the docs' screenshots (tools/console_screenshots.py)
drive: Debian's chromium-headless-shell, installed by tools/system-deps, started with what a root CI user needs
and nothing that reaches out (Playwright adds a fresh --user-data-dir itself)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium-headless-shell")
CHROMIUM_FLAGS = (
    "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync",
)  # fmt: skip


def launch_chromium(playwright: Any, **options: Any) -> Any:
    """A headless Chromium browser from a sync Playwright (`options`: Playwright's launch options, a timeout)."""
    return playwright.chromium.launch(
        executable_path=str(CHROMIUM), args=list(CHROMIUM_FLAGS), headless=True, **options
    )
