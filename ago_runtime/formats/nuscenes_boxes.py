"""The 3D boxes of a nuScenes-layout dataset (sample_annotation) and the rules that read classes off them.

- `CATEGORY_CLASS`: nuScenes category -> Occ3D class, as nuScenes-lidarseg's 16-class challenge maps them;
  categories it maps to "ignore" (police car, bicycle rack, debris, pushable/pullable, animals, strollers,
  wheelchairs, personal mobility) become `others`.
- `DatasetBoxes(root)`: every keyframe's boxes as (box2global 4x4, size wlh, Occ3D class); `in_ego(token,
  ego2global)` gives them in a keyframe's ego frame, `by_instance(token, ego2global)` keyed by the object's
  instance token (its track over the keyframes: `ago pseudo-labels --moving track`). Needs the
  sample_annotation, instance and category tables.
- `inside_box(points, box2ego, wlh)`: which points lie in a box (x along its length l, y along its width w,
  z along its height h, each side grown by `BOX_MARGIN` 0.05 m).
- `GROUND_Z` (0.3 m): a return below it in the ego frame (whose origin is on the ground under the rear axle)
  and in no box is ground (`ground_returns`). The boxes segmenter paints such returns as driveable surface
  and `ago metric --lidar` scores them apart from the rest.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.formats.nuscenes import find_version, load_table
from ago_runtime.formats.nuscenes_schema import quaternion_to_matrix

GROUND_Z = 0.3        # metres above the ego frame's ground plane
BOX_MARGIN = 0.05     # metres added to each side of a box when asking what lies inside it
BOX_TABLES = ("sample_annotation", "instance", "category")

CATEGORY_CLASS = {
    "human.pedestrian.adult": "pedestrian", "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian", "human.pedestrian.police_officer": "pedestrian",
    "vehicle.car": "car", "vehicle.motorcycle": "motorcycle", "vehicle.bicycle": "bicycle",
    "vehicle.bus.bendy": "bus", "vehicle.bus.rigid": "bus", "vehicle.truck": "truck",
    "vehicle.construction": "construction_vehicle", "vehicle.trailer": "trailer",
    "movable_object.barrier": "barrier", "movable_object.trafficcone": "traffic_cone",
}
OTHER_CLASS = "others"   # what every other category becomes
# the classes a box can give, in Occ3D order
BOX_CLASSES = ("others", "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian",
               "traffic_cone", "trailer", "truck")

Box = tuple[np.ndarray, np.ndarray, str]    # (box2frame 4x4, size (w, l, h), Occ3D class)


def box_tables_missing(root: str | Path) -> list[str]:
    """The box tables (BOX_TABLES) a nuScenes-layout dataroot lacks."""
    table_dir = Path(root) / find_version(Path(root))
    return [t for t in BOX_TABLES if not (table_dir / f"{t}.json").is_file()]


class DatasetBoxes:
    """Every keyframe's annotated boxes of a nuScenes-layout dataroot (see the module doc)."""

    def __init__(self, root: str | Path, needed_by: str = "the boxes", hint: str = ""):
        root = Path(root)
        table_dir = root / find_version(root)
        missing = box_tables_missing(root)
        if missing:
            raise AgoInputError(table_dir / f"{missing[0]}.json", f"{needed_by} needs the box tables "
                                f"{', '.join(t + '.json' for t in missing)} (missing){hint}")
        categories = {r["token"]: r["name"] for r in load_table(table_dir, "category")}
        instance_class = {r["token"]: CATEGORY_CLASS.get(categories.get(r.get("category_token"), ""), OTHER_CLASS)
                          for r in load_table(table_dir, "instance")}
        self.boxes: dict[str, list[Box]] = {}   # sample token -> boxes in the global frame
        self.instances: dict[str, list[str]] = {}   # sample token -> each box's instance token (boxes' order)
        for r in load_table(table_dir, "sample_annotation"):
            m = np.eye(4)
            m[:3, :3] = quaternion_to_matrix(r["rotation"])
            m[:3, 3] = r["translation"]
            cls = instance_class.get(r.get("instance_token"), OTHER_CLASS)
            self.boxes.setdefault(r["sample_token"], []).append((m, np.asarray(r["size"], float), cls))
            self.instances.setdefault(r["sample_token"], []).append(str(r.get("instance_token", "")))

    def in_ego(self, token: str, ego2global: np.ndarray) -> list[Box]:
        """(box2ego 4x4, size wlh, Occ3D class) of a keyframe's annotations, in its ego frame."""
        global2ego = np.linalg.inv(ego2global)
        return [(global2ego @ m, wlh, cls) for m, wlh, cls in self.boxes.get(token, [])]

    def by_instance(self, token: str, ego2global: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """instance token -> (box2ego 4x4, size wlh) of a keyframe's annotations in the frame `ego2global` maps
        from (another keyframe's ego frame too: the object's track across keyframes). Boxes without an instance
        token are left out."""
        global2ego = np.linalg.inv(ego2global)
        return {inst: (global2ego @ m, wlh) for inst, (m, wlh, _) in zip(self.instances.get(token, []),
                                                                         self.boxes.get(token, [])) if inst}


def inside_box(points: np.ndarray, box2ego: np.ndarray, wlh, margin: float = BOX_MARGIN) -> np.ndarray:
    """(N,) bool: the points (N, 3, ego frame) inside the box (each side grown by `margin` metres)."""
    local = (np.asarray(points, np.float64) - box2ego[:3, 3]) @ box2ego[:3, :3]
    half = np.array([wlh[1], wlh[0], wlh[2]], np.float64) / 2 + margin
    return np.all(np.abs(local) <= half, axis=1)


def return_classes(points: np.ndarray, boxes: list[Box]) -> np.ndarray:
    """(N,) object array: the Occ3D class of the box each point lies in ("" for none; a point in several
    boxes takes the last one's)."""
    out = np.full(len(points), "", dtype=object)
    for m, wlh, cls in boxes:
        out[inside_box(points, m, wlh)] = cls
    return out


def ground_returns(points: np.ndarray, boxes: list[Box], ground_z: float = GROUND_Z) -> np.ndarray:
    """(N,) bool: ground returns, below `ground_z` in the ego frame and in no box."""
    low = np.asarray(points)[:, 2] < ground_z
    for m, wlh, _ in boxes:
        low &= ~inside_box(points, m, wlh)
    return low
