"""Multi-frame aggregation: label each frame's LiDAR with its own images, then superimpose the
frames in the keyframe's ego frame.

`lift_frame(frame, segmenter, embedder)` -> `LiftedFrame`: the frame's own (keyframe) LiDAR sweep,
the points kept (ego-body returns dropped), each point's label-space class (255 = none) from the
frame's own six images, the camera and pixel of each point, and the frame's feature maps.

`lift_frame_and_sweeps(frame, segmenter, nonkey)`: the same for the keyframe's sweep and for non-key
LiDAR sweeps recorded before it (real nuScenes lists ~9 between two keyframes), all labelled with the
keyframe's images.

`frames_to_aggregate(ds, i, num_keyframes, interval)`: keyframe i first, then up to num_keyframes - 1
keyframes of the same scene at offsets +-interval*k, nearest first (ds.neighbours). The paper uses
30 frames, interval 2. Moving objects smear along their path: faithful to the paper.

`warp_to(lifted, key_ego2global)`: the lifted points in the keyframe's ego frame
(LidarSweep.points_in) and the LiDAR origin there.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.formats.frame import Frame, LidarSweep

from .backends import ImageEmbedder, Segmenter
from .lift import assign_cameras, lift_labels

# Returns from the ego car's own body are dropped (ego frame, metres; nuScenes' Renault Zoe about the
# rear-axle origin): x in [-1.0, 3.3], y in [-1.0, 1.0], z in [-0.5, 2.0].
EGO_BOX = ((-1.0, -1.0, -0.5), (3.3, 1.0, 2.0))


@dataclass
class LiftedFrame:
    sweep: LidarSweep
    keep: np.ndarray                 # (N_all,) bool: points of sweep.points that are used
    labels: np.ndarray               # (N,) uint8 label-space class of each kept point, 255 = none
    cam_idx: np.ndarray              # (N,) int8 camera (rig order) whose image the point is in, -1 = none
    uv: np.ndarray                   # (N, 2) float32 its position in that image (native pixels)
    feature_maps: list | None = None  # per camera (h, w, C) float32 map (None where no point falls), or None
    image_sizes: list | None = None   # per camera (width, height)

    @property
    def in_image(self) -> np.ndarray:
        return self.cam_idx >= 0

    @property
    def channels(self) -> int | None:
        if self.feature_maps is None:
            return None
        return next((m.shape[2] for m in self.feature_maps if m is not None), None)

    @property
    def num_points(self) -> int:
        return int(self.labels.shape[0])


def check_pose(sweep: LidarSweep, what: str) -> None:
    for name in ("ego2global", "lidar2ego"):
        m = getattr(sweep, name)
        if m is None or np.asarray(m).shape != (4, 4) or not np.all(np.isfinite(m)):
            raise AgoInputError(sweep.path or what, f"{what}: LiDAR sweep has no valid {name} pose")


def _kept_points(sweep: LidarSweep, key_ego2global: np.ndarray, ego_box) -> tuple[np.ndarray, np.ndarray]:
    """(keep (N_all,) bool, kept points (N, 3) in the keyframe's ego frame): finite points outside the
    ego body box (tested in the sweep's OWN ego frame, where the car's body is)."""
    own = sweep.points_ego()
    keep = np.all(np.isfinite(own), axis=1)
    if ego_box is not None:
        lo, hi = np.asarray(ego_box[0]), np.asarray(ego_box[1])
        keep &= ~np.all((own >= lo) & (own <= hi), axis=1)
    return keep, sweep.points_in(key_ego2global)[keep]


def lift_frame(frame: Frame, segmenter: Segmenter, embedder: ImageEmbedder | None = None,
               ego_box=EGO_BOX) -> LiftedFrame:
    """Label (and embed) one frame's own LiDAR points with its own images, all in its own ego frame."""
    return lift_frame_and_sweeps(frame, segmenter, [], embedder, ego_box)[0]


def lift_frame_and_sweeps(frame: Frame, segmenter: Segmenter, nonkey: list[LidarSweep],
                          embedder: ImageEmbedder | None = None, ego_box=EGO_BOX) -> list[LiftedFrame]:
    """The keyframe's own LiDAR points, then each non-key sweep of `nonkey` (e.g. the ~9 sweeps recorded
    between two nuScenes keyframes), all labelled with the KEYFRAME's six images: a non-key sweep's
    points are moved into the keyframe's ego frame through the two ego poses and projected into the
    keyframe cameras (static-world assumption over the < 0.5 s between them; moving objects smear,
    as they do across keyframes). One LiftedFrame per sweep, keyframe first; each keeps its own pose,
    so `warp_to` places it in any other keyframe's frame. Features (`embedder`) go to the keyframe's own.
    """
    if not frame.sweeps:
        raise AgoInputError(f"{frame.scene}/{frame.token}", "frame has no LiDAR sweep")
    where = f"{frame.scene}/{frame.token}"
    sweeps = [frame.lidar] + list(nonkey)
    parts = []
    for sweep in sweeps:
        check_pose(sweep, where)
        keep, pts = _kept_points(sweep, frame.ego2global if sweep is not frame.lidar else sweep.ego2global, ego_box)
        cam_idx, uv = assign_cameras(pts, frame.rig)
        parts.append((sweep, keep, cam_idx, uv))
    seen = [any(bool(np.any(c == ci)) for _, _, c, _ in parts) for ci in range(len(frame.rig.cameras))]
    maps = [segmenter.segment(frame, cam.name) if s else None for cam, s in zip(frame.rig, seen)]
    sizes = [(cam.width, cam.height) for cam in frame.rig]
    lifted = [LiftedFrame(sweep, keep, lift_labels(cam_idx, uv, maps), cam_idx.astype(np.int8), uv.astype(np.float32),
                          None, sizes) for sweep, keep, cam_idx, uv in parts]
    if embedder is not None:
        lifted[0] = attach_features(frame, lifted[0], embedder)
    return lifted


def attach_features(frame: Frame, lifted: LiftedFrame, embedder: ImageEmbedder) -> LiftedFrame:
    """A copy of `lifted` with the frame's feature maps ((h, w, C) float32 per camera that sees a point).

    Voxel sums are taken later (lift.feature_sums_per_voxel), so no per-point feature array is made.
    """
    seen = [bool(np.any(lifted.cam_idx == ci)) for ci in range(len(frame.rig.cameras))]
    maps = [np.ascontiguousarray(np.moveaxis(np.asarray(embedder.embed(frame, cam.name), dtype=np.float32), 0, -1))
            if s else None for cam, s in zip(frame.rig, seen)]
    return replace(lifted, feature_maps=maps)


def warp_to(lifted: LiftedFrame, key_ego2global: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kept points in the keyframe's ego frame (N, 3) float64, and this sweep's LiDAR origin there (3,)."""
    pts = lifted.sweep.points_in(key_ego2global)[lifted.keep]
    m = np.linalg.inv(key_ego2global) @ lifted.sweep.ego2global @ lifted.sweep.lidar2ego
    return pts, m[:3, 3].copy()


def frames_to_aggregate(ds, i: int, num_keyframes: int, interval: int) -> list[int]:
    """Keyframe i, then num_keyframes - 1 same-scene neighbours at +-interval*k (nearest first)."""
    if num_keyframes < 1:
        raise AgoInputError("--keyframes", f"must be >= 1 (the keyframe counts), got {num_keyframes}")
    return [i] + [j for j in ds.neighbours(i, num_keyframes - 1, interval) if j != i]
