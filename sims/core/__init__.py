"""Taichi start-up, caches, field io, scans and hashing: what every model stands on."""
