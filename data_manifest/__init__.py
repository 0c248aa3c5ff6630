"""The contract between the renderer and training: the sweep grid, the render manifest schema and
the registry of external data products (products.yaml)."""
