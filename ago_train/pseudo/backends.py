"""The two things a 2-D vision-language model gives AGO, as two small interfaces, and the file backends.

- `Segmenter.segment(frame, camera) -> (H, W) uint8`: a label map at the camera's native image
  size (frame.rig[camera].width x height); values are class indices of the label space
  (0..K-1), 255 = no label.
- `ImageEmbedder.embed(frame, camera) -> (C, h, w) float`: a dense feature map at any stride
  (cell (j, i) covers image pixels [i*W/w, (i+1)*W/w) x [j*H/h, (j+1)*H/h)).

File backends read what a GPU user produced once with Grounded SAM / MaskCLIP+FeatUp (exact
layout in docs/vlm_files.md):

    <masks_root>/classes.json               {"1": "car", "2": "sidewalk", ...}  id -> prompt phrase
    <masks_root>/<CAM>/<image stem>.png     uint8 label map (or .npy), same size as the image;
                                            0 = no label (255 is read as no label too)
    <feats_root>/<CAM>/<image stem>.npy     (C, h, w) float16/float32 feature map, any stride
    <feats_root>/meta.json                  optional: {"channels": C, ...}

`<image stem>` is the camera image's file name without its extension (nuScenes:
`n015-2018-07-24-11-22-45+0800__CAM_FRONT__1532402927612460`). Simulated backends for synthetic
data live in `simulated.py`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.readers import read_json
from ago_runtime.formats.frame import Frame
from ago_runtime.vocab.prompts import LabelSpace, name_key

NO_LABEL = 255
FILE_NO_LABEL = 0  # the id that means "no label" in label-map files (255 is accepted as well)


@runtime_checkable
class Segmenter(Protocol):
    name: str

    def config_dict(self) -> dict: ...

    def segment(self, frame: Frame, camera: str) -> np.ndarray: ...


@runtime_checkable
class ImageEmbedder(Protocol):
    name: str

    def config_dict(self) -> dict: ...

    def embed(self, frame: Frame, camera: str) -> np.ndarray: ...


def image_stem(frame: Frame, camera: str) -> str:
    """The file-name stem of a frame's camera image: the key of its mask / feature files."""
    path = frame.image_paths.get(camera)
    if not path:
        raise AgoInputError(f"{frame.scene}/{frame.token}", f"no image path for {camera}; file backends "
                            "name their files after the camera image")
    return Path(path).stem


def phrase_lookup(label_space: LabelSpace) -> dict[str, int]:
    """Phrase or class name (case/space-insensitive) -> class index of the label space."""
    table = {name_key(c.name): i for i, c in enumerate(label_space.classes)}
    for phrase, cls in zip(label_space.phrases, label_space.phrase_class):
        table[name_key(phrase)] = int(cls)
    return table


class FileSegmenter:
    """Label maps written by an external segmenter (Grounded SAM: box threshold 0.2, text threshold 0.15)."""

    name = "files"

    def __init__(self, masks_root: str | Path, label_space: LabelSpace):
        self.root = Path(masks_root)
        self.label_space = label_space
        if not self.root.is_dir():
            raise AgoInputError(self.root, "masks folder not found")
        classes_path = self.root / "classes.json"
        table = read_json(classes_path, missing="missing: it maps the ids in the label maps to prompt phrases")
        if not isinstance(table, dict):
            raise AgoInputError(classes_path, 'expected an object {"1": "car", ...}')
        lookup = phrase_lookup(label_space)
        self.lut = np.full(256, -1, dtype=np.int16)   # file id -> class index; -1 = id not declared
        self.lut[FILE_NO_LABEL] = NO_LABEL
        self.lut[255] = NO_LABEL
        self.classes = {}
        for key, phrase in table.items():
            if not (isinstance(key, str) and key.isdigit() and 1 <= int(key) <= 254):
                raise AgoInputError(classes_path, f"id {key!r}: ids must be 1..254 (0 and 255 mean no label)")
            if not isinstance(phrase, str):
                raise AgoInputError(classes_path, f"id {key}: expected a phrase string, got {phrase!r}")
            cls = lookup.get(name_key(phrase))
            if cls is None:
                raise AgoInputError(classes_path, f"id {key}: {phrase!r} is neither a phrase nor a class name "
                                    f"of label space {label_space.name!r}")
            self.lut[int(key)] = cls
            self.classes[int(key)] = phrase

    def config_dict(self) -> dict:
        return {"masks_root": str(self.root.resolve()), "classes": {str(k): v for k, v in self.classes.items()}}

    def path_for(self, frame: Frame, camera: str) -> Path:
        stem = image_stem(frame, camera)
        for ext in (".png", ".npy"):
            p = self.root / camera / f"{stem}{ext}"
            if p.is_file():
                return p
        raise AgoInputError(self.root / camera / f"{stem}.png", "label map not found (nor .npy)")

    def segment(self, frame: Frame, camera: str) -> np.ndarray:
        path = self.path_for(frame, camera)
        if path.suffix == ".png":
            from ago_runtime.formats.image_files import decode_image

            try:
                data = path.read_bytes()
            except OSError as e:
                raise AgoInputError(path, f"cannot read the label map ({e.strerror or e})") from None
            m = decode_image(data, path, cv2.IMREAD_UNCHANGED)   # header size limit, corrupt data refused
        else:
            from ago_runtime.readers import read_npy

            m = read_npy(path, "label map (.npy)")
        if m.ndim != 2 or m.dtype not in (np.uint8, np.int32, np.int64, np.uint16, np.int16):
            raise AgoInputError(path, f"expected an (H, W) integer label map, got {m.shape} {m.dtype}")
        if m.size and (m.min() < 0 or m.max() > 255):
            raise AgoInputError(path, f"label ids must lie in 0..255, found {m.min()}..{m.max()}")
        cam = frame.rig[camera]
        if m.shape != (cam.height, cam.width):
            raise AgoInputError(path, f"label map is {m.shape[1]}x{m.shape[0]} but the image is "
                                f"{cam.width}x{cam.height}")
        out = self.lut[m.astype(np.int64)]
        if np.any(out < 0):
            bad = sorted(set(np.unique(m[out < 0]).tolist()))
            raise AgoInputError(path, f"ids {bad[:10]} are not declared in {self.root / 'classes.json'}")
        return out.astype(np.uint8)


class FileImageEmbedder:
    """Dense image features written by an external model (MaskCLIP+ upsampled by FeatUp, GaussTR's script...)."""

    name = "files"

    def __init__(self, feats_root: str | Path, channels: int | None = None):
        self.root = Path(feats_root)
        if not self.root.is_dir():
            raise AgoInputError(self.root, "features folder not found")
        meta_path = self.root / "meta.json"
        self.meta = {}
        if meta_path.is_file():
            self.meta = read_json(meta_path)
            if channels is None and isinstance(self.meta.get("channels"), int):
                channels = self.meta["channels"]
        self.channels = channels  # None: taken from the first file read; later files must match
        enc = self.meta.get("encoder_id")
        self.encoder_id = enc if isinstance(enc, str) else None   # folders from before: None (width checked only)

    def probe_channels(self) -> int | None:
        """The channel count (meta.json's, else the first map's header), before any sample is made."""
        if self.channels is None:
            first = next((f for cam in sorted(p for p in self.root.iterdir() if p.is_dir())
                          for f in cam.glob("*.npy")), None)
            if first is not None:
                try:
                    f = np.load(first, allow_pickle=False, mmap_mode="r")
                except (ValueError, OSError) as e:
                    raise AgoInputError(first, f"not a readable .npy ({e})") from None
                if f.ndim == 3:
                    self.channels = int(f.shape[0])
        return self.channels

    def config_dict(self) -> dict:
        return {"feats_root": str(self.root.resolve()), "channels": self.channels,
                "meta": self.meta}

    def embed(self, frame: Frame, camera: str) -> np.ndarray:
        path = self.root / camera / f"{image_stem(frame, camera)}.npy"
        from ago_runtime.readers import read_npy

        f = read_npy(path, "feature map")   # its header checked before the data is read
        if f.ndim != 3 or f.dtype not in (np.float16, np.float32):
            raise AgoInputError(path, f"expected a (C, h, w) float16/float32 feature map, got {f.shape} {f.dtype}")
        if self.channels is None:
            self.channels = int(f.shape[0])
        elif f.shape[0] != self.channels:
            raise AgoInputError(path, f"feature map has {f.shape[0]} channels, expected {self.channels}")
        if f.shape[1] < 1 or f.shape[2] < 1:
            raise AgoInputError(path, f"empty feature map {f.shape}")
        f = np.asarray(f)
        if not np.all(np.isfinite(f)):
            raise AgoInputError(path, "feature map contains NaN or inf")
        return f


def embedder_encoder_id(embedder) -> str | None:
    """The encoder whose space an embedder's features lie in, when known: its `encoder_id` (MaskCLIP: the CLIP folder's
    id; files: meta.json's, None for folders without one); the simulated embedder's is its texts' encoder (MiniLM
    unless it names another as `text_encoder`)."""
    if embedder.name == "simulated":
        from ago_runtime.vocab.text_encoder import MINILM_ID

        return getattr(embedder, "text_encoder", None) or MINILM_ID
    return getattr(embedder, "encoder_id", None)


def check_features_fit_bank(features: str, feat_encoder_id: str | None, feat_channels: int | None, bank: str,
                            bank_encoder_id: str, bank_dim: int, source=None) -> None:
    """One `error:` line, naming both, unless image features can be aligned with a text bank: the same width and,
    when the features record one, the same encoder (`encoder_id`). Features that record no encoder (folders made
    before encoder ids, or by other scripts) pass when their width fits."""
    from ago_runtime.vocab.model_folder import check_same_encoder

    if feat_channels is not None and int(feat_channels) != int(bank_dim):
        raise AgoInputError(source, f"{features} are {int(feat_channels)}-d (encoder {feat_encoder_id or 'not recorded'}) "
                            f"but {bank} is {int(bank_dim)}-d (encoder {bank_encoder_id!r}); they must come from the "
                            "same model")
    if feat_encoder_id is not None:
        check_same_encoder(features, feat_encoder_id, bank, bank_encoder_id, source)
