"""A real headless Chromium (Debian's ``chromium``, driven by Playwright) that may read only one folder.

Every request the page makes goes through :func:`open_page`'s router: a ``file://`` URL inside the folder is
served, anything else (another folder, the network) is refused and recorded in ``outside``.
"""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from pathlib import Path
from urllib.parse import unquote, urlparse

ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def chromium_path() -> str | None:
    """The system's Chromium, or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def why_not() -> str | None:
    """Why the browser tests cannot run here (None when they can)."""
    if chromium_path() is None:
        return "no Chromium on this machine (apt-get install chromium; CI installs it in .ci/run)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "Playwright for Python is not installed (requirements-dev.txt)"
    return None


@contextmanager
def open_page(folder: Path, width: int = 1200, height: int = 800):
    """``(page, requests, outside)``: a page of ``width`` x ``height`` that may read only ``folder``."""
    from playwright.sync_api import sync_playwright

    root = folder.resolve()
    requests, outside = [], []

    def route(r):
        url = r.request.url
        requests.append(url)
        parsed = urlparse(url)
        if parsed.scheme == "file" and Path(unquote(parsed.path)).resolve().is_relative_to(root):
            return r.continue_()
        outside.append(url)
        return r.abort()

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium_path(), args=ARGS)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.route("**/*", route)
            yield page, requests, outside
        finally:
            browser.close()
