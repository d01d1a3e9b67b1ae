"""Products: folders with a manifest (manifests), the files other tools open (rasters), and the
canvas pictures are drawn on (canvas)."""
