"""Browser tests of the dashboard (headless Chromium through Playwright)."""
