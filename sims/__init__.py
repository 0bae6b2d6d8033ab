"""Simulation core: texture-space tissue surface, cautery, display. No web or CLI code."""
