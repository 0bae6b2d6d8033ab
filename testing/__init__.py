"""Support code the tests and the tools share: Debian chromium driven by Playwright (browser), a raw websocket client of
viser (raw_client), synthetic parameter sets and signals (helpers). Not installed with the lab: run from the repository."""
