"""Terrain: from a DEM on disk to the patch the renderer meshes.

- ``dem``: ingest any raster GDAL reads in a lunar CRS; checks and one-line errors.
- ``register``: register an elevation crop without (or with doubtful) georeferencing.
- ``stack``: finer DEM layers blended over the base DEM; ``stack_report``: its seam metrics.
- ``detail``: seeded sub-DEM roughness and small craters (fitted to real LOLA by
  ``crater_synth.tools.detail_calibration``).
- ``patch``: the curved near field plus the far field, in a local east-north-up frame.
- ``catalogue``: the crater catalogue, each entry checked as a closed depression of its size.
"""
