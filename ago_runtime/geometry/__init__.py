"""ago_runtime.geometry: the grid and the cameras, as numbers (no files, no pictures).

Holds `grid` (Grid: range and voxel size -> shape, voxel centres, world <-> index), `camera`
(Camera, Rig: intrinsics, cam2ego, the ego2img projections; the camera names) and `preprocess`
(Preprocess: the resize + ImageNet normalisation shared by training and the runtime, intrinsics
scaled to match).

May import: numpy, OpenCV and ago_runtime's basics (errors, atomic, readers, outputs, progress,
classes). Nothing else in ago_runtime.
"""
