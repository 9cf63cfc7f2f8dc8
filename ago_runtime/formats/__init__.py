"""ago_runtime.formats: the files ago reads and writes as datasets, and the keyframe they give.

Holds `occ3d` (Occ3D labels.npz), `frame` (Frame: one keyframe, images + rig + LiDAR + poses +
optional GT), `image_files` (safe JPEG / PNG decoding), `calibration` (images folder + calib.json
for `ago infer --images`), `nuscenes_schema` / `nuscenes` / `nuscenes_writer` (the nuScenes table
layout: schema, reader -> Frame, writer), `mmdet3d_info` (mmdetection3d info .pkl files) and
`occ3d_waymo` / `occ3d_waymo_writer` (Occ3D-Waymo ground-truth files; the synthetic Waymo layout).

May import: numpy, OpenCV, ago_runtime's basics and ago_runtime.geometry.
"""
