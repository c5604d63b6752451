"""COLMAP's bundle adjuster with the model-plane residual blocks: the Ceres problem, the steps of
the refine loop, the record it returns."""
