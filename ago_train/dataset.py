"""Training / evaluation samples: frames + 3D pseudo-labels + voxel VLM embeddings (E_3D) + GT.

`OccSampleDataset(frames, pseudo, label_space, grid, preprocess, ...)` is a torch Dataset; item i:

- "images": (V, 3, H, W) float32 (V cameras, the rig's order), `ago_runtime.geometry.preprocess.Preprocess` (identical to the runtime);
  or, with a `feature_cache` (ago_train/feature_cache.py), instead of the images "prefix": the frozen
  backbone stages' maps, a list of (V, C_l, H_l, W_l) float16 tensors (the JPEGs are not decoded);
- "ego2img": (V, 4, 4) float32, ego -> canvas projections (the rig's order);
- "semantics": (N,) int64 pseudo-label per voxel of the model grid (N = X*Y*Z, C order over [x,y,z]),
  as stored: 0..K-1 class, 17 = free, 255 = unknown, plus 254 = hit by the LiDAR but unlabelled
  (ago_runtime.classes.OCCUPIED_UNLABELLED; the losses map it: `pseudo_to_target` here does
  the same mapping to 0..K-1 / K free / IGNORE_INDEX for evaluation code);
- "e3d_index": (M,) int64 flat voxel indices with a lifted VLM embedding; "e3d_embeds": (M, C) float32;
- "gt": (Xg, Yg, Zg) uint8 Occ3D GT mapped to the label space (0..K-1, K = free, 255 = ignore) and
  "gt_mask": (Xg, Yg, Zg) bool camera-visibility mask — only when `with_gt` and the frame has GT;
- "token", "scene": strings.

`collate(items)` stacks the fixed-size tensors ("images" (B, V, 3, H, W) or "prefix" [(B, V, C_l, H_l, W_l)],
"ego2img", "semantics" (B, N))
and concatenates E_3D as the losses want it: "align_index" (sum M,) int64 indices into the batch's
B*N voxels (b * N + voxel) and "align_embed" (sum M, C) float32. GT stays a list of numpy arrays
(evaluation only).

Pseudo-label directory layout (written by `ago pseudo-labels`): meta.json (label space classes, grid),
`<scene>/<token>/labels.npz` (semantics: 0..K-1 class, 17 = free, 255 = unknown; masks) and
`<scene>/<token>/embeds.npz` (index (M,) int32, embeds (M, C) float16).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ago_runtime.classes import FREE, IGNORE, OCCUPIED_UNLABELLED
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid
from ago_runtime.geometry.preprocess import Preprocess

from .pseudo.generate import PseudoLabelDir

IGNORE_INDEX = -100  # torch's cross-entropy default


# ---- the pseudo-label directory ---------------------------------------------------------------
class PseudoLabelSet(PseudoLabelDir):
    """The pseudo-label folder as training reads it: `PseudoLabelDir` plus checks against the model.

    `labels` returns only the semantics (checked against the grid); `embeds` returns int64 indices
    and float32 embeddings, or empty arrays when the folder has no embeddings.
    """

    @classmethod
    def open(cls, root: str | Path) -> "PseudoLabelSet":
        root = Path(root)
        if not root.is_dir():
            raise AgoInputError(root, "pseudo-label directory not found (make it with `ago pseudo-labels`)")
        pseudo = cls(root)
        try:
            pseudo.grid, pseudo.class_names
        except (KeyError, TypeError, ValueError) as e:
            raise AgoInputError(root / "meta.json", f"meta.json lacks the grid or the label space ({e})") from None
        return pseudo

    def check(self, grid: Grid, class_names: Sequence[str]) -> None:
        """Refuse a pseudo-label set made for another grid or another label space."""
        mine = self.grid
        if tuple(mine.shape) != tuple(grid.shape) or not np.allclose(mine.range_min, grid.range_min) \
                or not np.allclose(mine.range_max, grid.range_max):
            raise AgoInputError(self.root / "meta.json",
                                f"pseudo-labels are on grid {mine.shape} {mine.range_min}..{mine.range_max} "
                                f"but the model grid is {grid.shape} {grid.range_min}..{grid.range_max}; "
                                "regenerate them with the model's grid")
        if list(self.class_names) != list(class_names):
            raise AgoInputError(self.root / "meta.json",
                                f"pseudo-labels use the classes {self.class_names} but the prompt file has "
                                f"{list(class_names)}; regenerate them with this prompt file")

    def sample_dir(self, scene: str, token: str) -> Path:
        return self.root / scene / token

    def has(self, scene: str, token: str) -> bool:
        return (self.sample_dir(scene, token) / "labels.npz").is_file()

    def labels(self, scene: str, token: str, mark_unlabelled_hits: bool = False) -> np.ndarray:
        """(X, Y, Z) uint8 pseudo semantics (0..K-1, 17 = free, 255 = unknown). With `mark_unlabelled_hits`,
        voxels the LiDAR hit (mask_lidar) that no mask labelled become OCCUPIED_UNLABELLED (254) instead of
        255: occupied for the occupancy loss, ignored by the grounding loss (training reads them so)."""
        path = self.sample_dir(scene, token) / "labels.npz"
        if not path.is_file():
            raise AgoInputError(path, "pseudo-label file not found (was `ago pseudo-labels` run on this frame?)")
        sem, mask_lidar, _ = super().labels(scene, token)
        if tuple(sem.shape) != tuple(self.grid.shape):
            raise AgoInputError(path, f"semantics shape {sem.shape} does not match the grid {self.grid.shape}")
        if mark_unlabelled_hits:
            # mask_lidar = crossed by a ray or hit; a crossed-but-not-hit voxel is free, so 255 there = a hit
            sem = np.where((sem == IGNORE) & (mask_lidar > 0), OCCUPIED_UNLABELLED, sem).astype(np.uint8)
        return sem

    def embeds(self, scene: str, token: str) -> tuple[np.ndarray, np.ndarray]:
        """(M,) int64 flat voxel indices and (M, C) float32 VLM embeddings; empty when the file is absent."""
        path = self.sample_dir(scene, token) / "embeds.npz"
        if not path.is_file():
            return np.zeros(0, np.int64), np.zeros((0, 0), np.float32)
        idx, emb = super().embeds(scene, token)
        idx = idx.astype(np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= self.grid.num_voxels):
            raise AgoInputError(path, f"voxel indices outside 0..{self.grid.num_voxels - 1}")
        return idx, emb.astype(np.float32)


# ---- label mapping ----------------------------------------------------------------------------
def pseudo_to_target(sem: np.ndarray, num_classes: int) -> np.ndarray:
    """Pseudo semantics (0..K-1, 17 free, 255 unknown) -> (N,) int64 targets (0..K-1, K free, IGNORE_INDEX)."""
    s = sem.reshape(-1).astype(np.int64)
    out = np.full(s.shape, IGNORE_INDEX, dtype=np.int64)
    cls = s < num_classes
    if num_classes > FREE:  # 17 would be ambiguous between a class and free; the label space forbids it
        raise AgoInputError(None, f"label spaces with more than {FREE} classes are not supported by the pseudo format")
    out[cls & (s != FREE)] = s[cls & (s != FREE)]
    out[s == FREE] = num_classes
    return out


def gt_to_label_space(gt_semantics: np.ndarray, lut: np.ndarray) -> np.ndarray:
    """Occ3D ids (0..16, 17 free, 255) -> label-space ids through `lut` = LabelSpace.gt_lut(free_index=K)
    (0..K-1 class, K free, 255 ignore)."""
    lut = np.asarray(lut)
    if lut.shape != (256,):
        raise ValueError(f"gt lut must have 256 entries, got {lut.shape}")
    return lut.astype(np.uint8)[gt_semantics.astype(np.uint8)]


# ---- the dataset -------------------------------------------------------------------------------
class OccSampleDataset(torch.utils.data.Dataset):
    """Frames (a sequence of ago_runtime Frame) joined with their pseudo-labels. See the module docstring."""

    def __init__(self, frames, pseudo: PseudoLabelSet | None, num_classes: int, grid: Grid,
                 preprocess: Preprocess, gt_lut: np.ndarray | None = None, with_gt: bool = False,
                 with_embeds: bool = True, color_jitter: float = 0.0, seed: int = 0, feature_cache=None,
                 memory_bytes: int = 0, augment: str = "none", camera_names: Sequence[str] | None = None):
        """camera_names: the model's cameras in its input order (its checkpoint's rig); every frame's rig is put
        in that order and a frame whose cameras differ is refused, naming the camera. None: each frame's own."""
        self.frames = frames
        self.camera_names = list(camera_names) if camera_names is not None else None
        self.pseudo = pseudo
        self.num_classes = int(num_classes)
        self.grid = grid
        self.preprocess = preprocess
        self.gt_lut = gt_lut
        self.with_gt = with_gt
        self.with_embeds = with_embeds
        self.color_jitter = float(color_jitter)
        self.seed = int(seed)
        self.epoch = 0
        self.feature_cache = feature_cache
        if feature_cache is not None and self.color_jitter > 0:
            raise ValueError("colour jitter changes the images, so their frozen features cannot be cached")
        # items are the same every epoch unless colour jitter changes them: keep up to `memory_bytes`
        # of them in memory, so later epochs read no file (pseudo-labels, E_3D, LiDAR, GT)
        self.memory_bytes = int(memory_bytes)
        self._memory: dict[int, dict] = {}
        self._memory_used = 0
        from .augment import draw

        draw(augment, 0, 0, 0)  # refuses an unknown kind now
        self.augment = augment

    def __len__(self) -> int:
        return len(self.frames)

    def set_epoch(self, epoch: int) -> None:
        """Augmentations draw from a generator seeded by (seed, epoch, index): reproducible on resume."""
        self.epoch = int(epoch)

    def __getitem__(self, i: int) -> dict:
        """The item of frame i, mirrored / turned by this epoch's draw of `augment` (augment.py)."""
        from .augment import draw

        key = self.frames.key(i) if hasattr(self.frames, "key") else i   # repeats of a frame share one copy
        base = self._memory.get(key)
        if base is None:
            base = self._load(i)
            if self.memory_bytes > 0 and self.color_jitter == 0:
                size = sum(t.numel() * t.element_size() for t in _tensors(base))
                if self._memory_used + size <= self.memory_bytes:
                    self._memory[key] = base
                    self._memory_used += size
        t = draw(self.augment, self.seed, self.epoch, i)
        item = dict(base)
        if self.feature_cache is not None:   # the cache keeps its own in-memory copy of recent frames
            item["prefix"] = [torch.from_numpy(m) for m in
                              self.feature_cache.frame_prefix(base["_image_paths"], base["_rig"], base["_source"],
                                                             flip=t.flip_y)]
        if t.identity:
            return item
        shape = tuple(self.grid.shape)
        item["ego2img"] = torch.from_numpy(t.ego2img(base["ego2img"].numpy(), self.preprocess.width))
        if "images" in item and t.flip_y:
            item["images"] = item["images"].flip(-1).contiguous()
        if "semantics" in item:
            item["semantics"] = torch.from_numpy(t.volume(base["semantics"].numpy().reshape(shape)).reshape(-1))
        if "e3d_index" in item:
            item["e3d_index"] = torch.from_numpy(t.flat_index(base["e3d_index"].numpy(), shape))
        for key in ("gt", "gt_mask"):
            if key in item:
                item[key] = t.volume(item[key])
        return item

    def rig_of(self, frame):
        """The frame's rig in the model's camera order (`camera_names`)."""
        if self.camera_names is None:
            return frame.rig
        return frame.rig.ordered_as(self.camera_names, f"{frame.scene}/{frame.token}")

    def _load(self, i: int) -> dict:
        frame = self.frames[i]
        source = f"{frame.scene}/{frame.token}"
        rig = self.rig_of(frame)
        item = {
            "ego2img": torch.from_numpy(self.preprocess.ego2img(rig)),
            "token": frame.token,
            "scene": frame.scene,
            "_image_paths": dict(frame.image_paths),
            "_rig": rig,   # in the model's camera order (the cached prefix is read with it, no frame re-read)
            "_source": source,
        }
        if self.feature_cache is None:
            images = self.preprocess.images(frame.images, rig, source=source)
            if self.color_jitter > 0:
                rng = np.random.default_rng([self.seed, self.epoch, int(i)])
                a = 1.0 + rng.uniform(-self.color_jitter, self.color_jitter, size=(len(images), 1, 1, 1)).astype(np.float32)
                b = rng.uniform(-self.color_jitter, self.color_jitter, size=(len(images), 1, 1, 1)).astype(np.float32)
                images = images * a + b
            item["images"] = torch.from_numpy(np.ascontiguousarray(images))
        if self.pseudo is not None:
            sem = self.pseudo.labels(frame.scene, frame.token, mark_unlabelled_hits=True)
            item["semantics"] = torch.from_numpy(sem.reshape(-1).astype(np.int64))
            if self.with_embeds:
                idx, emb = self.pseudo.embeds(frame.scene, frame.token)
                item["e3d_index"] = torch.from_numpy(idx)
                item["e3d_embeds"] = torch.from_numpy(emb)
        if self.with_gt:
            if frame.gt is None:
                raise AgoInputError(source, "frame has no Occ3D ground truth (needed for evaluation)")
            if self.gt_lut is None:
                raise ValueError("with_gt needs gt_lut (LabelSpace.gt_lut(free_index=K))")
            item["gt"] = gt_to_label_space(frame.gt.semantics, self.gt_lut)
            item["gt_mask"] = frame.gt.mask_camera.astype(bool)
        return item


def _tensors(item: dict):
    for v in item.values():
        if isinstance(v, torch.Tensor):
            yield v
        elif isinstance(v, list):
            yield from (t for t in v if isinstance(t, torch.Tensor))


def collate(items: list[dict]) -> dict:
    """Batch a list of items (see module docstring); E_3D padded with a validity mask."""
    out: dict = {
        "ego2img": torch.stack([it["ego2img"] for it in items]),
        "token": [it["token"] for it in items],
        "scene": [it["scene"] for it in items],
    }
    if all("images" in it for it in items):
        out["images"] = torch.stack([it["images"] for it in items])
    if all("prefix" in it for it in items):
        out["prefix"] = [torch.stack([it["prefix"][j] for it in items]) for j in range(len(items[0]["prefix"]))]
    if all("semantics" in it for it in items):
        out["semantics"] = torch.stack([it["semantics"] for it in items])
    if all("e3d_index" in it for it in items):
        n = int(items[0]["semantics"].shape[0]) if "semantics" in items[0] else 0
        out["align_index"] = torch.cat([it["e3d_index"].long() + b * n for b, it in enumerate(items)])
        out["align_embed"] = torch.cat([it["e3d_embeds"].float() for it in items])
    if all("gt" in it for it in items):
        out["gt"] = [it["gt"] for it in items]
        out["gt_mask"] = [it["gt_mask"] for it in items]
    return out


class FrameList:
    """A sequence view of a frame source restricted to some indices (e.g. a split or a few-shot subset)."""

    def __init__(self, source, indices: Sequence[int]):
        self.source = source
        self.indices = [int(i) for i in indices]

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int):
        return self.source[self.indices[i]]

    def key(self, i: int) -> int:
        """The frame's index in the source (repeated indices name one frame)."""
        return self.indices[i]
