"""Blood: the bleeding-method protocol and registry, the particles with their splat, and the height field."""
