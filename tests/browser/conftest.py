"""Browser fixtures: headless Chromium (Debian's /usr/bin/chromium) driven by Playwright; screenshots dir."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


@pytest.fixture(scope="session")
def artifacts(repo_root: Path) -> Path:
    """test-artifacts/ (gitignored) for screenshots."""
    d = repo_root / "test-artifacts"
    d.mkdir(exist_ok=True)
    return d


@pytest.fixture(scope="session")
def browser() -> Iterator[object]:
    """A headless Chromium; fails with the install command when it is missing."""
    from playwright.sync_api import sync_playwright

    if not shutil.which(CHROMIUM):
        pytest.fail(f"{CHROMIUM} is missing: apt-get install -y chromium", pytrace=False)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


# (base URL, token) -> a context manager giving a logged-in dashboard page and the page errors it raises
DashboardPage = Callable[[str, str], AbstractContextManager[tuple[Any, list[str]]]]


@pytest.fixture()
def dashboard_page(browser: Any) -> DashboardPage:
    """Opens the dashboard of a live server in a fresh browser context and logs in with a token."""

    @contextmanager
    def open_page(base: str, token: str) -> Iterator[tuple[Any, list[str]]]:
        ctx = browser.new_context(viewport={"width": 1280, "height": 900})
        try:
            page = ctx.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"{base}/ui/")
            page.fill("#login-token", token)
            page.click("#login-submit")
            yield page, errors
        finally:
            ctx.close()

    return open_page
