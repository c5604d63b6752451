"""The refined, georeferenced COLMAP model and the files people look at."""
