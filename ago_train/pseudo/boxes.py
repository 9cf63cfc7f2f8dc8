"""`--segmenter boxes`: label maps painted from the dataset's own 3D boxes and LiDAR ground points.

A stand-in for a vision-language segmenter on real nuScenes-layout data, so the whole real chain runs
without one. It is NOT a VLM and is named "boxes" everywhere (pseudo-label meta.json, bundle card:
"labels from dataset boxes").

For a keyframe and a camera it gives, like every `Segmenter`, an (H, W) uint8 map of label-space class
indices (255 = no label) at the camera's native size:
1. ground: the keyframe LiDAR returns with ego-frame z < `GROUND_Z` (0.3 m; the ego frame's origin is
   on the ground under the rear axle) that lie in no box (`formats.nuscenes_boxes.ground_returns`, the rule
   `ago metric --lidar` scores ground rays by) are projected into the image and each paints a
   disc of `GROUND_RADIUS_PX` pixels at 1600 px width (scaled with the image) as `driveable_surface`;
2. boxes: every sample_annotation of the keyframe (global centre, size w l h, rotation) is moved into the
   keyframe's ego frame, its surface sampled every 0.1 m, the points in front of the camera projected,
   and their convex hull filled with the box's class; boxes are painted far to near (by the distance of
   their centre from the camera), so nearer boxes cover farther ones.
Pixels neither step paints stay 255 (no label): buildings, vegetation, sky are not labelled.

Box classes: `ago_runtime.formats.nuscenes_boxes.CATEGORY_CLASS` (nuScenes categories -> Occ3D classes as
nuScenes-lidarseg's 16-class challenge maps them; the categories it ignores are painted `others`); the boxes
are read by its `DatasetBoxes`. A class the prompt file does not cover is not painted. Needs the
sample_annotation, instance and category tables (a trimmed extract usually has them).

With `masks_out` (`ago pseudo-labels --segmenter boxes --write-masks DIR`) every label map it paints is
also written in the label-map layout of docs/vlm_files.md, so the file backend reads it back as it is
(`--segmenter files --masks DIR` gives the same pseudo-labels): DIR/classes.json maps id k + 1 to the
name of label-space class k, DIR/<camera>/<image stem>.png holds the ids (0 = no label), 8-bit, at the
image's size. Each file is written atomically; a folder whose classes.json says otherwise is refused.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_bytes, write_json
from ago_runtime.errors import AgoInputError
from ago_runtime.readers import read_json
from ago_runtime.classes import OCC3D_ID
from ago_runtime.formats.frame import Frame
from ago_runtime.formats.nuscenes_boxes import GROUND_Z, DatasetBoxes, ground_returns
from ago_runtime.vocab.prompts import LabelSpace

from .backends import FILE_NO_LABEL, NO_LABEL, image_stem   # files: 0 = no label; class k is written as k + 1

GROUND_RADIUS_PX = 6     # disc radius per ground return at 1600 px image width
SURFACE_STEP = 0.1       # metres between sampled points on a box's faces
GROUND_CLASS = "driveable_surface"


def label_map_classes(label_space: LabelSpace) -> dict[str, str]:
    """classes.json of written label maps: id k + 1 (a string) -> the name of label-space class k."""
    return {str(k + 1): c.name for k, c in enumerate(label_space.classes)}


def to_file_ids(labels: np.ndarray) -> np.ndarray:
    """A segmenter's map (class indices, 255 = no label) -> label-map file ids (k + 1, 0 = no label)."""
    return np.where(labels == NO_LABEL, FILE_NO_LABEL, labels.astype(np.int32) + 1).astype(np.uint8)


def check_masks_dir(masks_out: str | Path, label_space: LabelSpace) -> Path:
    """`masks_out` as a Path; refuse a folder whose classes.json maps the ids otherwise (nothing is written
    here: the folder and its classes.json are made with the first label map)."""
    root = Path(masks_out)
    path = root / "classes.json"
    if path.is_file() and read_json(path) != label_map_classes(label_space):
        raise AgoInputError(path, f"maps the ids otherwise than label space {label_space.name!r} needs "
                            f"({label_map_classes(label_space)}); give an empty --write-masks folder")
    return root


def box_corners_sampler(size_wlh) -> np.ndarray:
    """(N, 3) points on the surface of a box of size (w, l, h) centred at 0, x along l, y along w."""
    w, l, h = (float(v) for v in size_wlh)
    axes = [np.linspace(-a / 2, a / 2, max(2, int(np.ceil(a / SURFACE_STEP)) + 1)) for a in (l, w, h)]
    pts = []
    for axis in range(3):
        others = [axes[i] for i in range(3) if i != axis]
        g = np.stack(np.meshgrid(*others, indexing="ij"), -1).reshape(-1, 2)
        for side in (axes[axis][0], axes[axis][-1]):
            p = np.insert(g, axis, side, axis=1)
            pts.append(p)
    return np.concatenate(pts)


class BoxSegmenter:
    """Label maps from the dataset's 3D boxes and LiDAR ground (see the module doc)."""

    name = "boxes"

    def __init__(self, data_root: str | Path, label_space: LabelSpace, masks_out: str | Path | None = None):
        root = Path(data_root)
        self.dataset_boxes = DatasetBoxes(root, "--segmenter boxes", "; use --segmenter files --masks DIR")
        lut = label_space.gt_lut()
        self.class_index = {c: int(lut[OCC3D_ID[c]]) for c in OCC3D_ID if c != "free"}
        self.root = root
        # where painted maps are also written (the file layout), or None; not part of config_dict: it
        # does not change the labels, so a resumed run may add or drop it
        self.masks_out = check_masks_dir(masks_out, label_space) if masks_out is not None else None
        self.masks_classes = label_map_classes(label_space)

    def write_label_map(self, frame: Frame, camera: str, labels: np.ndarray) -> Path:
        """Write `labels` as masks_out/<camera>/<image stem>.png (docs/vlm_files.md layout), atomically."""
        path = self.masks_out / camera / f"{image_stem(frame, camera)}.png"
        ok, png = cv2.imencode(".png", to_file_ids(labels))
        if not ok:
            raise AgoInputError(path, "could not encode the label map as PNG")
        path.parent.mkdir(parents=True, exist_ok=True)
        if not (self.masks_out / "classes.json").is_file():
            write_json(self.masks_out / "classes.json", self.masks_classes)
        write_bytes(path, png.tobytes())
        return path

    def config_dict(self) -> dict:
        return {"source": "dataset boxes (sample_annotation) + LiDAR ground, not a VLM",
                "ground_z": GROUND_Z, "ground_radius_px": GROUND_RADIUS_PX, "surface_step": SURFACE_STEP}

    def frame_boxes(self, frame: Frame) -> list[tuple[np.ndarray, np.ndarray, str]]:
        """(box2ego 4x4, size wlh, Occ3D class) of the keyframe's annotations, in its ego frame."""
        return self.dataset_boxes.in_ego(frame.token, frame.ego2global)

    def segment(self, frame: Frame, camera: str) -> np.ndarray:
        labels = self.paint(frame, camera)
        if self.masks_out is not None:
            self.write_label_map(frame, camera, labels)
        return labels

    def paint(self, frame: Frame, camera: str) -> np.ndarray:
        """The label map of one camera image (see the module doc)."""
        cam = frame.rig[camera]
        out = np.full((cam.height, cam.width), NO_LABEL, np.uint8)
        boxes = self.frame_boxes(frame)
        ground = self.class_index[GROUND_CLASS]
        if ground != NO_LABEL and frame.sweeps:
            pts = frame.lidar.points_in(frame.ego2global)
            low = pts[ground_returns(pts, boxes)]     # low returns in no box (a box's returns are the object's)
            uv, _, ok = cam.project(low)
            radius = max(1, int(round(GROUND_RADIUS_PX * cam.width / 1600)))
            mask = np.zeros(out.shape, np.uint8)
            for u, v in uv[ok].astype(np.int32):
                cv2.circle(mask, (int(u), int(v)), radius, 1, -1)
            out[mask > 0] = ground
        order = []
        for m, wlh, cls in boxes:
            index = self.class_index[cls]
            if index == NO_LABEL:
                continue
            centre_cam = cam.ego2cam[:3, :3] @ m[:3, 3] + cam.ego2cam[:3, 3]
            order.append((float(np.linalg.norm(centre_cam)), m, wlh, index))
        order.sort(key=lambda item: -item[0])          # far to near
        for _, m, wlh, index in order:
            pts = box_corners_sampler(wlh) @ m[:3, :3].T + m[:3, 3]
            c = pts @ cam.ego2cam[:3, :3].T + cam.ego2cam[:3, 3]
            front = c[:, 2] > 0.1
            if front.sum() < 3:
                continue
            uv = c[front] @ cam.intrinsics.T
            uv = uv[:, :2] / uv[:, 2:3]
            uv = np.clip(uv, -4 * cam.width, 5 * cam.width)     # far off-image points: keep the hull finite
            hull = cv2.convexHull(np.round(uv).astype(np.int32))
            cv2.fillConvexPoly(out, hull, int(index))
        return out
