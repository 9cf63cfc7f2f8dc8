"""Grounded SAM and MaskCLIP as `ago pseudo-labels` backends (`--segmenter grounded-sam`, `--embedder maskclip`).

The same code as `ago vlm-files` (grounded_sam.py, maskclip.py), run on the fly instead of through files:

- the models load once per process, on first use (`jobs > 1`: once per worker; the backends travel to workers as
  their settings only);
- each camera image is computed once: its label map / feature map is kept (label maps PNG-compressed) keyed by the
  image file, so the keyframes a sample superimposes and the next sample's neighbours reuse it. `computed` counts
  the images a backend really ran on.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.formats.calibration import read_image
from ago_runtime.formats.frame import Frame
from ago_runtime.vocab.prompts import LabelSpace

from .grounded_sam import GroundedSam, GroundedSamConfig
from .maskclip import DEFAULT_WIDTH, MaskClip

NO_LABEL = 255
MEMO_IMAGES = 1024   # label maps kept (compressed, ~10-60 kB each) / feature maps kept (float16, ~1.3 MB at 512x27x48)
MEMO_FEATURES = 64


def sized_image(img: np.ndarray | None, path, width: int, height: int) -> np.ndarray:
    """An (H, W, 3) RGB camera image (read from `path` when `img` is None), refused unless it is width x height."""
    img = read_image(path) if img is None else img
    if img.shape[:2] != (height, width):
        raise AgoInputError(path, f"image is {img.shape[1]}x{img.shape[0]} but its calibration says {width}x{height}")
    return img


def camera_image(frame: Frame, camera: str) -> np.ndarray:
    """The frame's camera image (RGB), checked against the rig's size."""
    path = frame.image_paths.get(camera)
    if camera not in frame.images and not path:
        raise AgoInputError(f"{frame.scene}/{frame.token}", f"no image for {camera}")
    cam = frame.rig[camera]
    return sized_image(frame.images.get(camera), path, cam.width, cam.height)


def image_key(frame: Frame, camera: str) -> str:
    return str(frame.image_paths.get(camera) or f"{frame.scene}/{frame.token}/{camera}")


def resolve_torch_device(device: str):
    from .loading import resolve_device

    return resolve_device(device)


class GroundedSamSegmenter:
    """Segmenter: label-space class indices (255 = no label) from Grounded SAM's phrase label maps."""

    name = "grounded-sam"

    def __init__(self, detector: str | Path, sam: str | Path, label_space: LabelSpace, config: GroundedSamConfig,
                 device: str = "cpu"):
        from ago_runtime.vocab.model_folder import read_model_config

        config.check()
        read_model_config(detector, "--detector", "grounding-dino")   # the cheap checks, before any work
        read_model_config(sam, "--sam", "sam")
        resolve_torch_device(device)
        self.detector, self.sam = Path(detector), Path(sam)
        self.label_space, self.config, self.device = label_space, config, device
        self.lut = np.full(256, NO_LABEL, dtype=np.uint8)     # phrase id (k + 1) -> class index
        self.lut[1: 1 + len(label_space.phrases)] = label_space.phrase_class.astype(np.uint8)
        self._model: GroundedSam | None = None
        self._memo: OrderedDict[str, bytes] = OrderedDict()
        self.computed = 0

    def load(self) -> GroundedSam:
        """The models (loaded once per process): checks the folders, the tokenizer and the device."""
        if self._model is None:
            self._model = GroundedSam(self.detector, self.sam, self.label_space.phrases, self.config,
                                      resolve_torch_device(self.device))
        return self._model

    def __getstate__(self):   # workers get the settings and load the models themselves
        state = dict(self.__dict__)
        state["_model"], state["_memo"] = None, OrderedDict()
        return state

    def config_dict(self) -> dict:
        from ago_runtime.vocab.model_folder import folder_hash

        return {"detector": str(self.detector.resolve()), "detector_hash": folder_hash(self.detector)[:16],
                "sam": str(self.sam.resolve()), "sam_hash": folder_hash(self.sam)[:16], **self.config.to_dict()}

    def phrase_map(self, frame: Frame, camera: str) -> np.ndarray:
        """(H, W) uint8 phrase ids (0 = no label) of one camera image, computed once."""
        key = image_key(frame, camera)
        if key in self._memo:
            self._memo.move_to_end(key)
            return cv2.imdecode(np.frombuffer(self._memo[key], np.uint8), cv2.IMREAD_UNCHANGED)
        label = self.load().label_map(camera_image(frame, camera))
        self.computed += 1
        self._memo[key] = cv2.imencode(".png", label)[1].tobytes()
        while len(self._memo) > MEMO_IMAGES:
            self._memo.popitem(last=False)
        return label

    def segment(self, frame: Frame, camera: str) -> np.ndarray:
        return self.lut[self.phrase_map(frame, camera)]


class MaskClipEmbedder:
    """ImageEmbedder: MaskCLIP dense features (C, h, w) of the CLIP in `--clip`."""

    name = "maskclip"

    def __init__(self, clip: str | Path, device: str = "cpu", width: int = DEFAULT_WIDTH):
        from ago_runtime.vocab.model_folder import clip_encoder_id, read_model_config

        self.clip, self.device, self.width = Path(clip), device, int(width)
        cfg = read_model_config(self.clip, "--clip", "clip")
        resolve_torch_device(device)
        self.channels = int(cfg.get("projection_dim", 512))
        self.encoder_id = clip_encoder_id(self.clip)
        self._model: MaskClip | None = None
        self._memo: OrderedDict[str, np.ndarray] = OrderedDict()
        self.computed = 0

    def load(self) -> MaskClip:
        if self._model is None:
            self._model = MaskClip(self.clip, resolve_torch_device(self.device), self.width)
            self.channels = self._model.channels
        return self._model

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_model"], state["_memo"] = None, OrderedDict()
        return state

    def config_dict(self) -> dict:
        return {"clip": str(self.clip.resolve()), "encoder_id": self.encoder_id, "input_width": self.width}

    def embed(self, frame: Frame, camera: str) -> np.ndarray:
        key = image_key(frame, camera)
        if key in self._memo:
            self._memo.move_to_end(key)
            return self._memo[key]
        f = self.load().features(camera_image(frame, camera))
        self.computed += 1
        self._memo[key] = f
        while len(self._memo) > MEMO_FEATURES:
            self._memo.popitem(last=False)
        return f


def vlm_backends(label_space: LabelSpace, detector: Path | None, sam: Path | None, clip: Path | None, device: str,
                 config: GroundedSamConfig, clip_width: int = DEFAULT_WIDTH, load: bool = True
                 ) -> tuple[GroundedSamSegmenter | None, MaskClipEmbedder | None]:
    """The backends of the weight options (`--detector` and `--sam` together, `--clip`), models loaded (`load`):
    every folder, tokenizer and device problem is raised here, before any work."""
    if (detector is None) != (sam is None):
        missing = "--sam" if sam is None else "--detector"
        raise AgoInputError(missing, "Grounded SAM needs both --detector DIR (GroundingDINO) and --sam DIR (SAM)")
    seg = None if detector is None else GroundedSamSegmenter(detector, sam, label_space, config, device)
    emb = None if clip is None else MaskClipEmbedder(clip, device, clip_width)
    if load:
        for backend in (seg, emb):
            if backend is not None:
                backend.load()
    return seg, emb
