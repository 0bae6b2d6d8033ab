"""The look: the film of blood the display shows, the display tiles, and the composition of the PBR maps."""
