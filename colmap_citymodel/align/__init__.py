"""Reconstruction frame -> model frame: georegistration to GNSS, the coarse search against the
model surfaces, the similarity onto assigned planes."""
