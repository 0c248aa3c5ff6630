"""The registry of external data products (products.yaml): the embedded LOLA DEM and LROC WAC mosaic,
the full-resolution products the paper used, their sources, sizes and checksums."""
