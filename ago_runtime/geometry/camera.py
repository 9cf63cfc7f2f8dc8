"""Cameras and the surround rig.

Frames of reference (nuScenes conventions):
- camera frame: x right, y down, z forward (optical axis), metres;
- ego frame: x forward, y left, z up, origin at the rear axle centre on the ground;
- image: pixel (u, v), u right, v down, origin top-left corner of the top-left pixel
  (a pixel centre is at integer + 0.5 ... we follow nuScenes and treat K as mapping to
  continuous pixel coordinates; cv2 sampling at floor(u), floor(v)).

`ego2img` is the 4x4 matrix [K 0; 0 1] @ inv(cam2ego): ego point (x, y, z, 1) -> (u*d, v*d, d, 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ago_runtime.errors import AgoInputError

# cam2ego rotations may come rounded (calib.json files with 4 decimals): tolerance on R R^T = I.
ROTATION_TOLERANCE = 1e-2
MAX_CAMERA_OFFSET_M = 1e3   # a camera (cam2ego translation) farther than this from the ego origin is refused

MAX_CAMERAS = 12

# nuScenes' six cameras, in the order nuScenes readers build their rig
CAMERA_NAMES: tuple[str, ...] = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)


@dataclass
class Camera:
    name: str
    intrinsics: np.ndarray  # (3, 3) K, pixels
    cam2ego: np.ndarray     # (4, 4)
    width: int
    height: int

    def __post_init__(self):
        self.intrinsics = np.asarray(self.intrinsics, dtype=np.float64).reshape(3, 3)
        self.cam2ego = np.asarray(self.cam2ego, dtype=np.float64).reshape(4, 4)

    def validate(self, source: str | None = None) -> None:
        """Refuse NaN/inf or singular calibration, non-positive focal lengths, a cam2ego that is not a rigid
        transform (rotation within ROTATION_TOLERANCE), with a message naming `source`."""
        for what, m in (("intrinsics", self.intrinsics), ("cam2ego", self.cam2ego)):
            if not np.all(np.isfinite(m)):
                raise AgoInputError(source, f"{self.name} {what} contains NaN or inf")
        if np.abs(self.cam2ego[:3, 3]).max() > MAX_CAMERA_OFFSET_M:   # before any arithmetic that would overflow
            raise AgoInputError(source, f"{self.name} cam2ego: translation {self.cam2ego[:3, 3].tolist()} is more "
                                        f"than {MAX_CAMERA_OFFSET_M:g} m from the ego origin")
        if abs(np.linalg.det(self.intrinsics)) < 1e-9 or abs(np.linalg.det(self.cam2ego[:3, :3])) < 1e-6:
            raise AgoInputError(source, f"{self.name} calibration is singular")
        fx, fy = float(self.intrinsics[0, 0]), float(self.intrinsics[1, 1])
        if fx <= 0 or fy <= 0:
            raise AgoInputError(source, f"{self.name} intrinsics: focal lengths must be positive, got fx {fx:g}, fy {fy:g}")
        if not np.allclose(self.intrinsics[2], [0.0, 0.0, 1.0], atol=1e-6):
            raise AgoInputError(source, f"{self.name} intrinsics: last row must be [0, 0, 1], got {self.intrinsics[2].tolist()}")
        r = self.cam2ego[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=ROTATION_TOLERANCE) or np.linalg.det(r) < 0:
            raise AgoInputError(source, f"{self.name} cam2ego: its 3x3 part is not a rotation "
                                        f"(R R^T differs from I by more than {ROTATION_TOLERANCE}, or det < 0)")
        if not np.allclose(self.cam2ego[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
            raise AgoInputError(source, f"{self.name} cam2ego: last row must be [0, 0, 0, 1]")
        if self.width <= 0 or self.height <= 0:
            raise AgoInputError(source, f"{self.name} has a non-positive image size")

    @property
    def ego2cam(self) -> np.ndarray:
        return np.linalg.inv(self.cam2ego)

    @property
    def ego2img(self) -> np.ndarray:
        """(4, 4) ego -> homogeneous image coordinates (u*d, v*d, d, 1)."""
        k4 = np.eye(4)
        k4[:3, :3] = self.intrinsics
        return k4 @ self.ego2cam

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera with its image resized to (width, height): K scaled per axis."""
        sx, sy = width / self.width, height / self.height
        k = self.intrinsics.copy()
        k[0] *= sx
        k[1] *= sy
        return Camera(self.name, k, self.cam2ego.copy(), int(width), int(height))

    def project(self, points_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ego points (N, >=3) -> pixel uv (N, 2), depth (N,), and mask 'in front and inside the image'."""
        p = np.asarray(points_ego, dtype=np.float64)[:, :3]
        cam = p @ self.ego2cam[:3, :3].T + self.ego2cam[:3, 3]
        depth = cam[:, 2]
        safe = np.where(depth > 1e-6, depth, 1.0)
        uv = (cam @ self.intrinsics.T)[:, :2] / safe[:, None]
        ok = (depth > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height)
        return uv, depth, ok

    def to_dict(self) -> dict:
        return {"name": self.name, "intrinsics": self.intrinsics.tolist(), "cam2ego": self.cam2ego.tolist(),
                "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(d["name"], np.array(d["intrinsics"]), np.array(d["cam2ego"]), int(d["width"]), int(d["height"]))


def check_camera_names(have, wanted, source=None, whose: str = "model's") -> None:
    """Refuse cameras `have` that are not exactly `wanted` (a model's or bundle's rig, any order), naming the first
    camera that differs: one the rig takes and `have` lacks, then one `have` has and the rig does not."""
    have, wanted = list(have), list(wanted)
    for n in wanted:
        if n not in have:
            raise AgoInputError(source, f"camera {n}: the {whose} rig takes it and it is missing here")
    for n in have:
        if n not in wanted:
            raise AgoInputError(source, f"camera {n}: not a camera of the {whose} rig ({', '.join(wanted)})")


@dataclass
class Rig:
    """The cameras of one vehicle, in the order the model takes them: 1..MAX_CAMERAS cameras with distinct
    names, each with its own image size. Readers of nuScenes data build it in CAMERA_NAMES order; a
    calib.json or a dataset of another rig gives its own names and order."""

    cameras: list[Camera] = field(default_factory=list)

    def __post_init__(self):
        names = [c.name for c in self.cameras]
        if not 1 <= len(names) <= MAX_CAMERAS:
            raise AgoInputError(None, f"a rig needs 1..{MAX_CAMERAS} cameras, got {len(names)}")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise AgoInputError(None, f"camera {dup[0]}: named more than once in the rig")
        bad = [n for n in names if not isinstance(n, str) or not n or len(n) > 64 or not n.replace("_", "").isalnum()]
        if bad:
            raise AgoInputError(None, f"camera {bad[0]!r}: a camera name is 1..64 letters, digits or '_'")
        self.cameras = list(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def ordered_as(self, names, source=None) -> "Rig":
        """The same cameras in the order `names` gives (the rig a model was trained for); a camera missing here
        or one that `names` does not list is refused, naming it (`check_camera_names`)."""
        names = list(names)
        check_camera_names(self.names, names, source, whose="model's")
        return Rig([self[n] for n in names])

    def __getitem__(self, name: str) -> Camera:
        return {c.name: c for c in self.cameras}[name]

    def __iter__(self):
        return iter(self.cameras)

    def ego2img(self) -> np.ndarray:
        """(V, 4, 4) float32 projection matrices in the rig's order."""
        return np.stack([c.ego2img for c in self.cameras]).astype(np.float32)

    def validate(self, source: str | None = None) -> None:
        for c in self.cameras:
            c.validate(source)

    def to_dict(self) -> dict:
        return {"cameras": [c.to_dict() for c in self.cameras]}

    @classmethod
    def from_dict(cls, d: dict) -> "Rig":
        return cls([Camera.from_dict(c) for c in d["cameras"]])

    @classmethod
    def nuscenes_like(cls, width: int = 1600, height: int = 900) -> "Rig":
        """A rig with nuScenes' camera placement (scene-0061's calibration, rounded), scaled to (width, height).

        Yaws (degrees, ego frame, 0 = forward, positive = left): FRONT 0, FRONT_RIGHT -55,
        FRONT_LEFT 55, BACK 180, BACK_LEFT 110, BACK_RIGHT -110. Horizontal FOV 70 deg,
        BACK 110 deg, as in nuScenes.
        """
        spec = {  # name: (x, y, z, yaw_deg, hfov_deg)
            "CAM_FRONT": (1.70, 0.02, 1.51, 0.0, 64.5),
            "CAM_FRONT_RIGHT": (1.55, -0.49, 1.50, -56.0, 64.5),
            "CAM_FRONT_LEFT": (1.52, 0.49, 1.51, 55.0, 64.5),
            "CAM_BACK": (0.03, 0.00, 1.57, 180.0, 89.3),
            "CAM_BACK_LEFT": (1.04, 0.48, 1.56, 108.5, 64.5),
            "CAM_BACK_RIGHT": (1.01, -0.48, 1.56, -109.0, 64.5),
        }
        cams = []
        for name in CAMERA_NAMES:
            x, y, z, yaw, hfov = spec[name]
            cams.append(level_camera(name, x, y, z, np.deg2rad(yaw), np.deg2rad(hfov), 1600, 900).scaled(width, height))
        return cls(cams)


def level_camera(name: str, x: float, y: float, z: float, yaw: float, hfov: float, w: int, h: int) -> Camera:
    """A level camera at (x, y, z) in the ego frame looking along `yaw`."""
    f = (w / 2) / np.tan(hfov / 2)
    k = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    left = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    r = np.stack([-left, -up, forward], axis=1)  # camera axes (x right, y down, z fwd) in ego coords
    cam2ego = np.eye(4)
    cam2ego[:3, :3] = r
    cam2ego[:3, 3] = (x, y, z)
    return Camera(name, k, cam2ego, w, h)
