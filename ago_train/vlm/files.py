"""`ago vlm-files`: Grounded SAM label maps and MaskCLIP features for a dataset's camera images, as files.

Writes, for every camera image of the selected keyframes, exactly what `ago pseudo-labels --segmenter files --masks
OUT/masks --embedder files --feats OUT/feats` reads (docs/vlm_files.md):

    OUT/masks/classes.json            {"1": <phrase 1 of the prompt file>, ...}  one id per phrase (subclass phrases
                                      included, so a map says which prompt made each label)
    OUT/masks/<CAM>/<image stem>.png  8-bit label map at the image's size, 0 = no label
    OUT/feats/meta.json               channels, stride, input_width, model, encoder_id (clip_encoder_id of --clip)
    OUT/feats/<CAM>/<image stem>.npy  (C, h, w) float16 MaskCLIP features (with --clip)
    OUT/vlm_files.json                the settings (prompt file hash and phrases, model folder hashes, thresholds)

Nothing is written before the first image has been computed in memory (a bad folder, tokenizer, device or image
fails with nothing written). Resumable: an image whose files exist and read back sound (decodable, its size, ids
declared, feature shape and channels, finite) is skipped; a damaged one is made again; a folder made with other
settings is refused. Every file is written atomically.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_bytes, write_json
from ago_runtime.errors import AgoInputError
from ago_runtime.progress import track, track_rate
from ago_runtime.readers import read_json

from .backends import GroundedSamSegmenter, MaskClipEmbedder, sized_image

SETTINGS = "vlm_files.json"
FORMAT_VERSION = 1


@dataclass
class ImageJob:
    index: int        # dataset index of the keyframe
    camera: str
    stem: str         # image file stem: the files' name
    path: str         # the image file
    width: int        # its size from the calibration
    height: int


def image_jobs(ds, indices: list[int]) -> list[ImageJob]:
    """Every camera image of the keyframes `indices`, in dataset order then rig order."""
    from ago_train.pseudo.backends import image_stem

    jobs = []
    for i in indices:
        frame = ds[i]
        for cam in frame.rig:
            jobs.append(ImageJob(i, cam.name, image_stem(frame, cam.name), frame.image_paths[cam.name],
                                 cam.width, cam.height))
    return jobs


def settings_record(label_space, segmenter: GroundedSamSegmenter, embedder: MaskClipEmbedder | None) -> dict:
    return {"format_version": FORMAT_VERSION,
            "prompts": {"name": label_space.name, "sha256": label_space.sha256, "phrases": label_space.phrases},
            "grounded_sam": segmenter.config_dict(),
            "maskclip": None if embedder is None else embedder.config_dict()}


def _comparable(record: dict) -> dict:
    """The settings without the folders' paths (the same weights moved elsewhere are the same weights)."""
    r = json.loads(json.dumps(record))
    r.pop("created_by", None)
    for part in ("grounded_sam", "maskclip"):
        for key in ("detector", "sam", "clip"):
            (r.get(part) or {}).pop(key, None)
    return r


class VlmFolder:
    def __init__(self, out: str | Path, label_space, channels: int | None):
        self.out = Path(out)
        self.masks, self.feats = self.out / "masks", self.out / "feats"
        self.num_ids = len(label_space.phrases)
        self.channels = channels

    def mask_path(self, job: ImageJob) -> Path:
        return self.masks / job.camera / f"{job.stem}.png"

    def feat_path(self, job: ImageJob) -> Path:
        return self.feats / job.camera / f"{job.stem}.npy"

    def problem(self, job: ImageJob) -> str | None:
        """None when this image's files are there and sound, else what is wrong."""
        height, width = job.height, job.width
        path = self.mask_path(job)
        if not path.is_file():
            return "missing"
        m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if m is None or m.dtype != np.uint8 or m.shape != (height, width):
            return f"{path}: not an 8-bit {width}x{height} label map"
        if int(m.max(initial=0)) > self.num_ids:
            return f"{path}: ids above {self.num_ids}"
        if self.channels is None:
            return None
        path = self.feat_path(job)
        if not path.is_file():
            return "missing"
        try:
            f = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            return f"{path}: {e}"
        if f.ndim != 3 or f.shape[0] != self.channels or f.dtype != np.float16 or not np.all(np.isfinite(f)):
            return f"{path}: not a ({self.channels}, h, w) finite float16 map"
        return None

    def save(self, job: ImageJob, label: np.ndarray, feats: np.ndarray | None) -> None:
        """Feature map first, label map last (its presence marks the image done), each atomically."""
        if feats is not None:
            import io

            buf = io.BytesIO()
            np.save(buf, feats.astype(np.float16), allow_pickle=False)
            write_bytes(self.feat_path(job), buf.getvalue())
        write_bytes(self.mask_path(job), cv2.imencode(".png", label)[1].tobytes())


def write_vlm_files(ds, indices: list[int], out: str | Path, label_space, segmenter: GroundedSamSegmenter,
                    embedder: MaskClipEmbedder | None, command: str = "", progress: bool = True) -> dict:
    """Label maps (and features) of every camera image of keyframes `indices` into `out`; resumable; counts."""
    out = Path(out)
    settings = settings_record(label_space, segmenter, embedder)
    settings_path = out / SETTINGS
    if settings_path.is_file():
        old = read_json(settings_path)
        if not isinstance(old, dict) or _comparable(old) != _comparable(settings):
            raise AgoInputError(settings_path, "this folder holds label maps / features made with other settings "
                                "(prompts, model weights or thresholds); use another --out or delete it")
    elif (out / "masks").exists() or (out / "feats").exists():
        raise AgoInputError(out, f"holds masks/ or feats/ not made by `ago vlm-files` (no {SETTINGS}); use another "
                            "--out")
    jobs = image_jobs(ds, indices)
    folder = VlmFolder(out, label_space, embedder.channels if embedder is not None else None)
    todo, damaged = [], 0
    if settings_path.is_file():
        checked = track(jobs, "checking existing", total=len(jobs)) if progress else jobs
        for job in checked:
            problem = folder.problem(job)
            if problem is not None:
                todo.append(job)
                damaged += problem != "missing"
    else:
        todo = list(jobs)

    def compute(job: ImageJob):
        image = sized_image(None, job.path, job.width, job.height)
        label = segmenter.load().label_map(image)
        feats = embedder.load().features(image) if embedder is not None else None
        return label, feats

    t0 = time.perf_counter()
    written = 0
    if todo and not settings_path.is_file():
        label, feats = compute(todo[0])          # the settings work before anything is written
        out.mkdir(parents=True, exist_ok=True)
        write_json(folder.masks / "classes.json", {str(k + 1): p for k, p in enumerate(label_space.phrases)})
        if embedder is not None:
            write_json(folder.feats / "meta.json", {**embedder.load().meta(), "created_by": command})
        write_json(settings_path, {**settings, "created_by": command})
        folder.save(todo[0], label, feats)
        written, todo = 1, todo[1:]
    items = track_rate(todo, "vlm files", len(todo), "images") if progress else todo
    for job in items:
        label, feats = compute(job)
        folder.save(job, label, feats)
        written += 1
    seconds = time.perf_counter() - t0
    return {"images": len(jobs), "written": written, "skipped": len(jobs) - written, "remade": damaged,
            "seconds": round(seconds, 3), "images_per_s": round(written / seconds, 3) if written and seconds else None,
            "detector_passes": segmenter.load().num_passes if written else None}
