"""Image preprocessing shared by training and the runtime (so both see identical inputs).

`Preprocess` makes the model's input: one (3, height, width) canvas per camera, in the rig's order.
The rule for a rig whose cameras differ in image size (Occ3D-Waymo's side cameras are shorter) is
the one the Occ3D-Waymo loaders follow (pad to the largest size, then scale): the rig's largest
image (its widest width, its tallest height) fills the canvas, and every camera is scaled by the
same factors (width / largest width, height / largest height), placed at the canvas' top-left
corner, the rest left at 0 (the mean colour after normalising). A rig of one image size, as
nuScenes', fills every canvas. Resizing is cv2.INTER_AREA, RGB uint8 -> float32 normalised with
the ImageNet mean/std, NCHW. Each camera's intrinsics are scaled the same way (Camera.scaled), so
`ego2img` matches the canvas.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ago_runtime.geometry.camera import Rig
from ago_runtime.errors import AgoInputError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class Preprocess:
    width: int = 352
    height: int = 192
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD

    def camera_sizes(self, rig: Rig) -> list[tuple[int, int]]:
        """(width, height) each camera's image takes on its canvas, in the rig's order (the rule above)."""
        ref_w = max(c.width for c in rig)
        ref_h = max(c.height for c in rig)
        return [(max(1, min(self.width, int(round(c.width * self.width / ref_w)))),
                 max(1, min(self.height, int(round(c.height * self.height / ref_h))))) for c in rig]

    def images(self, images: dict[str, np.ndarray], rig: Rig, source: str | None = None) -> np.ndarray:
        """dict camera -> (H, W, 3) uint8 RGB  ->  (V, 3, height, width) float32 in the rig's order."""
        out = np.zeros((len(rig.cameras), 3, self.height, self.width), dtype=np.float32)
        mean = np.asarray(self.mean, dtype=np.float32) * 255.0
        inv_std = 1.0 / (np.asarray(self.std, dtype=np.float32) * 255.0)
        for i, (cam, (w, h)) in enumerate(zip(rig, self.camera_sizes(rig))):
            img = images.get(cam.name)
            if img is None:
                raise AgoInputError(source, f"camera {cam.name} is missing")
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise AgoInputError(source, f"camera {cam.name}: expected (H, W, 3) uint8, got {img.shape} {img.dtype}")
            if img.shape[:2] != (h, w):
                img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            # channel by channel into the (3, h, w) slots: the same (x - mean) * inv_std in float32, without
            # the strided transposed write that normalising (H, W, 3) would need
            for c, plane in enumerate(cv2.split(img)):
                np.subtract(plane, mean[c], out=out[i, c, :h, :w], dtype=np.float32)
                out[i, c, :h, :w] *= inv_std[c]
        return out

    def ego2img(self, rig: Rig) -> np.ndarray:
        """(V, 4, 4) float32 projections onto the canvases."""
        return Rig([c.scaled(w, h) for c, (w, h) in zip(rig, self.camera_sizes(rig))]).ego2img()

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "mean": list(self.mean), "std": list(self.std),
                "resize": "cv2.INTER_AREA", "channel_order": "RGB", "layout": "NCHW"}

    @classmethod
    def from_dict(cls, d: dict) -> "Preprocess":
        return cls(int(d["width"]), int(d["height"]), tuple(d["mean"]), tuple(d["std"]))
