"""`colmap-citymodel run`: from a folder of photographs to a refined, georeferenced block.

The steps, each reused when a previous run in the same output directory finished it:
image metadata (images.py), COLMAP's SIFT features (features.py), COLMAP's matching chosen
from the data (matching.py), COLMAP's incremental mapping with the city model inside
(mapper.py), refine (workflow.py) and the report (run.py)."""
