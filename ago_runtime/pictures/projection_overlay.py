"""A picture to check calibration by eye: the keyframe LiDAR projected into the rig's cameras.

Takes a `Frame` (images, rig, sweeps[0]); gives a PNG with the images in rows (`render.mosaic_layout`:
nuScenes' six as
    CAM_FRONT_LEFT  CAM_FRONT  CAM_FRONT_RIGHT
    CAM_BACK_LEFT   CAM_BACK   CAM_BACK_RIGHT
any other rig three to a row in its own order), each downscaled to `tile_width` pixels wide, with every LiDAR point that lands in the image drawn at
its pixel, coloured by its depth along the optical axis (turbo colour map: red near, blue at
`max_depth` metres and beyond). Points go LiDAR frame -> ego (lidar2ego) -> `Camera.project`, i.e. the
same geometry the rest of ago uses; if the calibration or a convention were wrong, the points would
not follow the edges of cars and buildings.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_bytes
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.frame import Frame
from ago_runtime.formats.nuscenes import read_jpeg_rgb
from ago_runtime.pictures.render import mosaic_layout


def depth_colors(depth: np.ndarray, max_depth: float) -> np.ndarray:
    """(N,) metres -> (N, 3) uint8 RGB, red near, blue far."""
    level = np.clip(255.0 * (1.0 - depth / max_depth), 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(level.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)
    return bgr[:, ::-1]


def render_depth_overlay(frame: Frame, out_png: str | Path | None = None, tile_width: int = 480,
                         max_depth: float = 60.0, radius: int = 1) -> np.ndarray:
    """Draw the overlay; write it to `out_png` (PNG) when given. Returns the (H, W, 3) uint8 RGB picture."""
    points_ego = frame.lidar.points_ego()
    rows = []
    for row in mosaic_layout(frame.rig.names):
        tiles = []
        for name in row:
            cam = frame.rig[name]
            image = frame.images.get(name)
            if image is None:
                if name not in frame.image_paths:
                    raise AgoInputError(None, f"frame {frame.token} has no {name} image")
                image = read_jpeg_rgb(frame.image_paths[name])
            scale = tile_width / cam.width
            tile_h = int(round(cam.height * scale))
            tile = cv2.resize(image, (tile_width, tile_h), interpolation=cv2.INTER_AREA)
            small = cam.scaled(tile_width, tile_h)
            uv, depth, ok = small.project(points_ego)
            order = np.argsort(-depth[ok])  # far first, so near points end on top
            uv, depth = uv[ok][order], depth[ok][order]
            colors = depth_colors(depth, max_depth)
            u = np.floor(uv[:, 0]).astype(np.int64)
            v = np.floor(uv[:, 1]).astype(np.int64)
            for du in range(-radius, radius + 1):
                for dv in range(-radius, radius + 1):
                    uu, vv = u + du, v + dv
                    inside = (uu >= 0) & (uu < tile_width) & (vv >= 0) & (vv < tile_h)
                    tile[vv[inside], uu[inside]] = colors[inside]
            cv2.putText(tile, f"{name} ({len(u)} pts)", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                        (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(tile)
        height = max(t.shape[0] for t in tiles)
        row_img = np.concatenate([np.pad(t, ((0, height - t.shape[0]), (0, 0), (0, 0))) for t in tiles], axis=1)
        rows.append(row_img)
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    picture = np.concatenate(rows, axis=0)
    if out_png is not None:
        ok, png = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(picture), cv2.COLOR_RGB2BGR))
        if not ok:
            raise AgoInputError(out_png, "cv2 could not encode the PNG")
        write_bytes(out_png, png.tobytes())
    return picture
