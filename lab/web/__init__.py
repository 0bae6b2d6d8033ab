"""The browser lab on viser: the app, the per-browser texture stream, and the guards on what a browser sends."""
