"""ago_runtime.pictures: images made for people - BEVs, voxel views, camera mosaics, charts, overlays.

Holds `render` (occupancy BEVs and 3-D voxel views, legends, mosaics, PNG writing), `charts` (line
charts, grouped bars and heatmaps drawn with OpenCV), `projection_overlay` (LiDAR projected into the rig's
cameras) and `cli` (`ago show`).

May import: numpy, OpenCV, ago_runtime's basics, geometry and formats; `cli` may also import
scoring and typer.
"""
