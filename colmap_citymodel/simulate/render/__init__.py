"""Rendered photographs of the simulator's true scene (`simulate --render`): JPEGs with EXIF GPS
and DJI XMP from the simulated GNSS, check-point targets painted on the surfaces and their
image positions as OpenDroneMap's gcp_list.txt; the truth beside them as the simulator writes
it. CPU only (open3d's RaycastingScene), no GPU or display."""
