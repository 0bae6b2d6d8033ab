"""The texture space of the tissue mesh: texel maps, resampling between grids, seam links, sleep tiles, ray casts and the texel-metric stencil."""
