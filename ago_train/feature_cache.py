"""Content-addressed cache of the frozen backbone stages' outputs (training only).

With `ModelConfig.frozen_stages >= 1` the first backbone stages never change during training, so
their output for one camera image is a pure function of (the image file's bytes, the frozen weights,
the preprocessing). `FeatureCache` computes it once per image, stores it as float16, and training
reads it instead of decoding six JPEGs and running those stages at every step.

- Key of an image: sha256 of its file's bytes (`image_key`), so a changed or renamed file can never
  be served a stale entry.
- Folder: `<root>/<fingerprint>/`, where the fingerprint hashes the frozen stages' parameters and
  buffers, the backbone name, `frozen_stages`, the preprocessing (`Preprocess.to_dict()`) and
  FORMAT_VERSION, plus for a ResNet the sha256 of its `backbone_weights` file and a non-default
  `backbone_style`: new weights (another weights file even with equal frozen stages) or a new image
  size go to a fresh folder.
- Entry: `<fingerprint>/<key[:2]>/<key>.npz` holding arrays `l0`, `l1`, ... ((C_l, H_l, W_l) float16,
  the maps of `backbone.frozen_prefix`), written atomically; on read the shapes and dtype are checked
  against the backbone's and the values must be finite, else the entry is recomputed.
- A frame's prefix (`frame_prefix`) = per level (V, C_l, H_l, W_l) float16 in the rig's camera order;
  `flip=True` gives the prefix of the images flipped left-right (the mirror augmentation,
  ago_train/augment.py), stored under `<key>-flip`.
  Recently used frames are also kept in memory (up to `memory_bytes`).

The cache is a training-time shortcut only: the exported model and the runtime always run the whole
backbone on the images (`AGOModel.forward(images, ...)`); `test_feature_cache_matches_images` checks
that a step from cached maps equals a step from the images to float16 precision.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from ago_runtime.atomic import save_npz, write_json
from ago_runtime.geometry.camera import Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.nuscenes import read_jpeg_rgb
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.predict.bundle import file_sha256

FORMAT_VERSION = 1


def default_cache_root() -> Path:
    """$AGO_CACHE_DIR/features, else ~/.cache/ago/features."""
    base = os.environ.get("AGO_CACHE_DIR")
    return (Path(base) if base else Path.home() / ".cache" / "ago") / "features"


def image_key(path: str | Path) -> str:
    """sha256 (hex) of an image file's bytes."""
    return file_sha256(path)


def backbone_fingerprint(model, preprocess: Preprocess) -> str:
    """sha256 (hex) of everything the frozen prefix depends on (weights, stages, preprocessing)."""
    backbone = model.backbone
    h = hashlib.sha256()
    head = {"format": FORMAT_VERSION, "backbone": model.cfg.backbone, "frozen_stages": int(backbone.frozen_stages),
            "preprocess": preprocess.to_dict()}
    # a ResNet's user weights file and style (only when set, so EfficientNet fingerprints stay as they were)
    if getattr(backbone, "weights_sha256", None):
        head["weights_sha256"] = backbone.weights_sha256
    if getattr(backbone, "style", "pytorch") != "pytorch":
        head["style"] = backbone.style
    h.update(json.dumps(head, sort_keys=True).encode())
    for name, t in sorted(backbone.frozen_state().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


class FeatureCache:
    """The frozen prefix of a model's backbone, per camera image, on disk (+ an in-memory LRU)."""

    def __init__(self, model, preprocess: Preprocess, root: str | Path | None = None,
                 memory_bytes: int = 2 << 30):
        if int(getattr(model.backbone, "frozen_stages", 0)) <= 0:
            raise ValueError("the backbone has no frozen stages: nothing to cache")
        self.model = model
        self.preprocess = preprocess
        self.fingerprint = backbone_fingerprint(model, preprocess)
        self.dir = Path(root or default_cache_root()) / self.fingerprint[:24]
        self.memory_bytes = int(memory_bytes)
        self._memory: OrderedDict[tuple, list[np.ndarray]] = OrderedDict()
        self._memory_used = 0
        self.shapes = self._expected_shapes()
        self.stats = {"computed": 0, "read": 0, "memory": 0, "rejected": 0}
        self.dir.mkdir(parents=True, exist_ok=True)
        meta = self.dir / "meta.json"
        if not meta.is_file():
            write_json(meta, {"format": FORMAT_VERSION, "fingerprint": self.fingerprint,
                              "backbone": model.cfg.backbone, "frozen_stages": int(model.backbone.frozen_stages),
                              "preprocess": preprocess.to_dict(),
                              "levels": [list(s) for s in self.shapes]})

    def _expected_shapes(self) -> list[tuple[int, int, int]]:
        x = torch.zeros(1, 3, self.preprocess.height, self.preprocess.width)
        with torch.no_grad():
            was = self.model.backbone.training
            self.model.backbone.eval()
            maps = self.model.backbone.frozen_prefix(x)
            self.model.backbone.train(was)
        return [tuple(int(v) for v in m.shape[1:]) for m in maps]

    # ------------------------------------------------------------------ one image
    def _path(self, key: str) -> Path:
        return self.dir / key[:2] / f"{key}.npz"

    def _read(self, key: str) -> list[np.ndarray] | None:
        path = self._path(key)
        if not path.is_file():
            return None
        from ago_runtime.readers import open_npz

        try:
            with open_npz(path, "feature cache entry") as z:
                maps = [np.asarray(z[f"l{i}"]) for i in range(len(self.shapes))]
        except Exception:  # noqa: BLE001 - any unreadable or oversized entry is recomputed
            maps = None
        if maps is None or any(m.dtype != np.float16 or tuple(m.shape) != s for m, s in zip(maps, self.shapes)) \
                or not all(np.isfinite(m).all() for m in maps):
            self.stats["rejected"] += 1
            return None
        return maps

    @torch.no_grad()
    def _compute(self, x: np.ndarray, flip: bool = False) -> list[np.ndarray]:
        """Preprocessed (V, 3, H, W) images -> per level (V, C, H, W) float16 (of the images flipped
        left-right with `flip`). The input goes in channels-last (the convolutions follow it, which is
        faster on a CPU; the maps agree with the NCHW run to ~1e-6 relative, far below float16's resolution)."""
        if flip:
            x = x[..., ::-1]
        x = torch.from_numpy(np.ascontiguousarray(x))
        backbone = self.model.backbone
        was = backbone.training
        backbone.eval()
        device = next(self.model.parameters()).device
        maps = backbone.frozen_prefix(x.to(device).contiguous(memory_format=torch.channels_last))
        backbone.train(was)
        return [m.cpu().contiguous().numpy().astype(np.float16) for m in maps]

    # ------------------------------------------------------------------ one frame
    def frame_prefix(self, image_paths: dict[str, str], rig: Rig, source: str = "", flip: bool = False) -> list[np.ndarray]:
        """The frozen prefix of a frame's images: per level (V, C_l, H_l, W_l) float16 in the rig's order."""
        return self.frame_prefixes(image_paths, rig, source, (flip,))[0]

    def frame_prefixes(self, image_paths: dict[str, str], rig: Rig, source: str = "",
                       flips: tuple[bool, ...] = (False,)) -> list[list[np.ndarray]]:
        """`frame_prefix` for each of `flips`; the JPEGs are hashed, decoded and preprocessed once."""
        names = rig.names
        missing = [c for c in names if c not in image_paths]
        if missing:
            raise AgoInputError(source or None, f"cameras {missing} have no image file")
        full = (self.preprocess.width, self.preprocess.height)
        # a camera that does not fill its canvas (a shorter image of the rig) keys its maps by its size there too
        base = [image_key(image_paths[c]) + ("" if wh == full else f"-{wh[0]}x{wh[1]}")
                for c, wh in zip(names, self.preprocess.camera_sizes(rig))]
        x = None   # the preprocessed images, decoded on the first miss
        out = []
        for flip in flips:
            keys = tuple(k + ("-flip" if flip else "") for k in base)
            if keys in self._memory:
                self._memory.move_to_end(keys)
                self.stats["memory"] += 1
                out.append(self._memory[keys])
                continue
            per_cam = [self._read(k) for k in keys]
            todo = [i for i, m in enumerate(per_cam) if m is None]
            if todo:
                if x is None:
                    x = self.preprocess.images({c: read_jpeg_rgb(image_paths[c]) for c in names}, rig,
                                               source=source)
                computed = self._compute(x, flip)
                for i in todo:
                    per_cam[i] = [m[i] for m in computed]
                    save_npz(self._path(keys[i]), compressed=False,
                             **{f"l{j}": np.ascontiguousarray(m[i]) for j, m in enumerate(computed)})
                self.stats["computed"] += len(todo)
            self.stats["read"] += len(names) - len(todo)
            maps = [np.stack([per_cam[i][j] for i in range(len(names))]) for j in range(len(self.shapes))]
            self._remember(keys, maps)
            out.append(maps)
        return out

    def _remember(self, keys: tuple, maps: list[np.ndarray]) -> None:
        size = sum(m.nbytes for m in maps)
        if size > self.memory_bytes:
            return
        self._memory[keys] = maps
        self._memory_used += size
        while self._memory_used > self.memory_bytes:
            _, old = self._memory.popitem(last=False)
            self._memory_used -= sum(m.nbytes for m in old)

    def fill(self, frames, progress: bool = True, flips: tuple[bool, ...] = (False,)) -> dict:
        """Make sure every frame (objects with `.image_paths`, `.scene`, `.token`) is cached (also flipped
        when `flips` holds True); returns stats."""
        from ago_runtime.progress import track

        items = range(len(frames))
        it = track(items, "caching frozen backbone features", total=len(frames)) if progress else items
        for i in it:
            f = frames[i]
            self.frame_prefixes(f.image_paths, f.rig, f"{f.scene}/{f.token}", tuple(flips))
        return dict(self.stats)
