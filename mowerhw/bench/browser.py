"""Headless Chromium for the status page's checks (issue 19): Debian's ``chromium`` driven by
Playwright with that executable (no browser download)."""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from collections.abc import Iterator
from typing import Any

#: flags for a machine with no network beyond localhost and no GPU (see the Playwright docs:
#: ``executable_path`` runs a system Chromium)
CHROMIUM_ARGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def chromium_path() -> str | None:
    """The system Chromium, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def missing() -> str:
    """Why a browser check cannot run here ('' when it can)."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the Python package playwright is not installed (pip install playwright)"
    if chromium_path() is None:
        return "no chromium on PATH (Debian: apt-get install chromium)"
    return ""


@contextlib.contextmanager
def page(url: str, width: int = 1280, height: int = 800) -> Iterator[Any]:
    """A Playwright page showing ``url`` in headless Chromium."""
    from playwright.sync_api import sync_playwright

    exe = chromium_path()
    if exe is None:
        raise RuntimeError(missing())
    with (
        tempfile.TemporaryDirectory(prefix="mowerhw-chromium-") as profile,
        sync_playwright() as pw,
    ):
        browser = pw.chromium.launch_persistent_context(
            profile,
            executable_path=exe,
            args=CHROMIUM_ARGS,
            headless=True,
            viewport={"width": width, "height": height},
            bypass_csp=True,  # the page forbids eval; Playwright's string predicates use it
        )
        try:
            pg = browser.new_page() if not browser.pages else browser.pages[0]
            pg.goto(url)
            yield pg
        finally:
            browser.close()
