"""Batch geo-registration: many COLMAP workspaces refined against one city model, on a local
process pool or a Dask cluster (`colmap-citymodel batch`, batch.run.main)."""
