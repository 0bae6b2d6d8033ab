"""The application: CLI, headless runner (browser app and benchmarks follow)."""
