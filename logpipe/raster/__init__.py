"""Ego-centred lane rasters: the rasteriser and the plain reference it is tested against, map layers prepared for
drawing, centre and heading rules, raster runs on disk, the per-shard render and the preview PNGs."""
