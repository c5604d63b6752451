"""The image block: the COLMAP reconstruction and its GNSS positions in the model CRS."""
