"""Image preprocessing shared by training and the runtime (so both see identical inputs).

`Preprocess` resizes each camera image to the model's input size with cv2.INTER_AREA,
converts RGB uint8 -> float32, normalises with ImageNet mean/std, and returns NCHW.
The rig's intrinsics are scaled the same way (Camera.scaled), so `ego2img` matches the
resized image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ago_runtime.geometry.camera import CAMERA_NAMES, Rig
from ago_runtime.errors import AgoInputError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class Preprocess:
    width: int = 352
    height: int = 192
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD

    def images(self, images: dict[str, np.ndarray], source: str | None = None) -> np.ndarray:
        """dict camera -> (H, W, 3) uint8 RGB  ->  (6, 3, height, width) float32, CAMERA_NAMES order."""
        out = np.empty((len(CAMERA_NAMES), 3, self.height, self.width), dtype=np.float32)
        mean = np.asarray(self.mean, dtype=np.float32) * 255.0
        inv_std = 1.0 / (np.asarray(self.std, dtype=np.float32) * 255.0)
        for i, name in enumerate(CAMERA_NAMES):
            if name not in images:
                raise AgoInputError(source, f"camera {name} is missing")
            img = images[name]
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise AgoInputError(source, f"camera {name}: expected (H, W, 3) uint8, got {img.shape} {img.dtype}")
            if img.shape[:2] != (self.height, self.width):
                img = cv2.resize(img, (self.width, self.height), interpolation=cv2.INTER_AREA)
            # channel by channel into the (3, H, W) slots: the same (x - mean) * inv_std in float32, without
            # the strided transposed write that normalising (H, W, 3) would need
            for c, plane in enumerate(cv2.split(img)):
                np.subtract(plane, mean[c], out=out[i, c], dtype=np.float32)
                out[i, c] *= inv_std[c]
        return out

    def ego2img(self, rig: Rig) -> np.ndarray:
        """(6, 4, 4) float32 projections onto the resized images."""
        return rig.scaled(self.width, self.height).ego2img()

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "mean": list(self.mean), "std": list(self.std),
                "resize": "cv2.INTER_AREA", "channel_order": "RGB", "layout": "NCHW"}

    @classmethod
    def from_dict(cls, d: dict) -> "Preprocess":
        return cls(int(d["width"]), int(d["height"]), tuple(d["mean"]), tuple(d["std"]))
