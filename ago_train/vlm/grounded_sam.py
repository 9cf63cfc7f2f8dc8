"""Grounded SAM from the user's folders: GroundingDINO boxes for a prompt file's phrases, SAM masks in them.

Per camera image (`GroundedSam.label_map(image) -> (H, W) uint8`, 0 = no label, k = phrase k-1 of the prompt file):

1. **One GroundingDINO pass with every phrase** of the label space (subclass phrases included), joined as
   "car. truck. driveable surface." (the caption form the model was trained on). A prompt file whose tokens do not
   fit the detector's text length (`max_text_len`, 256 for the published checkpoints) is split into chunks of whole
   phrases, one pass each; nothing is truncated.
2. **Each query's box -> a phrase through the phrase's token span** in the logits: the box score is the query's
   highest token probability (sigmoid of the logit), kept when above `box_threshold` (paper 0.2); its phrase is the
   one whose span holds the highest token probability, kept when that is above `text_threshold` (paper 0.15). The
   post-processor's `text_labels` (the decoded tokens above the threshold, joined) are not used: they are not class
   names.
3. **Non-maximum suppression** over all boxes (class-agnostic, IoU `nms_iou` 0.5: two phrases firing on one object
   keep the stronger) and at most `max_boxes` per image (highest scores).
4. **SAM** embeds the image once and decodes one mask per box (single-mask output), upscaled to the image; masks are
   painted from the lowest score up, so where they overlap the highest-scoring box wins.

Preprocessing follows each model's image processor (read from the folder's preprocessor_config.json when present,
else the published checkpoints' values), written here with opencv because transformers' image processors need
torchvision and PIL: GroundingDINO resizes the shorter side to 800 with the longer at most 1333; SAM resizes the
longer side to its vision config's image_size (1024) and pads to a square.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.model_folder import ARCHITECTURES

from .loading import load_model, mean_std, preprocessor_config, quiet_transformers, to_tensor

IMAGENET_MEAN, IMAGENET_STD = [0.485, 0.456, 0.406], [0.229, 0.224, 0.225]
MAX_PHRASES = 254            # label-map files hold ids 1..254 (0 and 255 mean no label)


@dataclass
class GroundedSamConfig:
    box_threshold: float = 0.2     # paper: Grounded SAM's box threshold
    text_threshold: float = 0.15   # paper: Grounded SAM's text threshold
    nms_iou: float = 0.5
    max_boxes: int = 64            # per camera image, after NMS (SAM's cost grows with it)

    def check(self) -> None:
        for name in ("box_threshold", "text_threshold", "nms_iou"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise AgoInputError("--" + name.replace("_", "-"), f"expected a value in 0..1, got {v}")
        if self.max_boxes < 1:
            raise AgoInputError("--max-boxes", f"expected at least 1, got {self.max_boxes}")

    def to_dict(self) -> dict:
        return asdict(self)


def detector_resize(height: int, width: int, shortest: int, longest: int) -> tuple[int, int]:
    """(h, w) GroundingDINO's processor resizes to: shorter side `shortest`, longer side at most `longest`."""
    short, long_ = min(height, width), max(height, width)
    size = float(shortest)
    if long_ / short * size > longest:
        size = longest * short / long_
    if height <= width:
        return max(1, int(round(size))), max(1, int(round(size * width / height)))
    return max(1, int(round(size * height / width))), max(1, int(round(size)))


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) IoU of xyxy boxes."""
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
    area = lambda x: np.prod(np.clip(x[:, 2:] - x[:, :2], 0, None), axis=1)   # noqa: E731
    return inter / np.maximum(area(a)[:, None] + area(b)[None] - inter, 1e-9)


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression, highest score first (ties: lower index first)."""
    order = np.lexsort((np.arange(len(scores)), -scores))
    keep = []
    suppressed = np.zeros(len(scores), dtype=bool)
    ious = box_iou(boxes, boxes)
    for i in order:
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= ious[i] > iou
    return np.asarray(keep, dtype=np.int64)


@dataclass
class Detections:
    boxes: np.ndarray    # (N, 4) float32 xyxy in image pixels
    scores: np.ndarray   # (N,) float32
    phrases: np.ndarray  # (N,) int64 phrase index into the prompt's phrases


class PhraseDetector:
    """GroundingDINO (`--detector DIR`) and its tokenizer, with the prompt's phrases split into passes."""

    option = "--detector"

    def __init__(self, folder: str | Path, phrases: list[str], device, model=None, tokenizer=None):
        """Loads the folder's model and tokenizer; `model` / `tokenizer` given: those (benchmarks/vlm_cost.py)."""
        quiet_transformers()
        from transformers import AutoTokenizer, GroundingDinoForObjectDetection

        self.folder = Path(folder)
        self.model = model if model is not None else load_model(GroundingDinoForObjectDetection, folder, self.option,
                                                                "grounding-dino", device)
        self.device = device
        self.tokenizer = self._tokenizer(AutoTokenizer, tokenizer)
        cfg = self.model.config
        self.max_text_len = int(cfg.max_text_len)
        pre = preprocessor_config(folder) if model is None else {}
        size = pre.get("size") or {}
        self.shortest = int(size.get("shortest_edge", 800))
        self.longest = int(size.get("longest_edge", 1333))
        self.mean, self.std = mean_std(pre, IMAGENET_MEAN, IMAGENET_STD, self.folder / "preprocessor_config.json")
        self.phrases = list(phrases)
        self.passes = self._passes()

    def _tokenizer(self, auto_tokenizer, tok=None):
        """The folder's tokenizer, refused unless it is a BERT-style one the model's text backbone can read: it has
        [CLS], [SEP] and "." (the caption's phrase separator) and all its ids fit the text embeddings. The model
        splits the caption into phrases at the ids of [CLS], [SEP], "." and "?" (a buffer transformers fills with
        bert-base-uncased's ids, 101, 102, 1012, 1029); it is set from this tokenizer, which for the published
        checkpoints changes nothing."""
        import torch

        expected = f"expected the tokenizer saved with {ARCHITECTURES['grounding-dino']} (bert-base-uncased)"
        if tok is None and not any((self.folder / n).is_file() for n in ("tokenizer.json", "vocab.txt")):
            raise AgoInputError(self.option, f"{self.folder}: no tokenizer (tokenizer.json or vocab.txt); {expected}")
        try:
            tok = tok if tok is not None else auto_tokenizer.from_pretrained(str(self.folder), local_files_only=True)
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else e.__class__.__name__
            raise AgoInputError(self.option, f"{self.folder}: no usable tokenizer ({first}); {expected}") from None
        if isinstance(tok, bool) or not hasattr(tok, "get_vocab"):
            raise AgoInputError(self.option, f"{self.folder}: no tokenizer files; {expected}")
        vocab = tok.get_vocab()
        missing = [name for name, tid in (("[CLS]", tok.cls_token_id), ("[SEP]", tok.sep_token_id),
                                          ('"."', vocab.get("."))) if tid is None]
        if missing:
            raise AgoInputError(self.option, f"{self.folder}: the tokenizer does not fit the detector: it has no "
                                f"{', '.join(missing)} token (GroundingDINO reads '[CLS] a. b. [SEP]'); {expected}")
        size = int(self.model.config.text_config.vocab_size)
        if len(tok) > size:
            raise AgoInputError(self.option, f"{self.folder}: the tokenizer does not fit the detector: {len(tok)} "
                                f"tokens but the text model embeds {size}; {expected}")
        special = [tok.cls_token_id, tok.sep_token_id, vocab["."], vocab.get("?", vocab["."])]
        buffer = self.model.model.special_tokens
        self.model.model.special_tokens = torch.tensor(special, dtype=buffer.dtype, device=buffer.device)
        return tok

    def _passes(self) -> list[dict]:
        """The phrases split into detector passes of at most max_text_len tokens ([CLS] ... [SEP]), whole phrases
        each: [{input_ids (1, T), spans [(phrase index, first token, end token)]}]."""
        pieces = []
        for k, phrase in enumerate(self.phrases):
            ids = self.tokenizer(phrase.lower().strip(), add_special_tokens=False)["input_ids"]
            if not ids:
                raise AgoInputError(self.option, f"the tokenizer of {self.folder} makes no tokens of phrase "
                                    f"{phrase!r}")
            if len(ids) + 3 > self.max_text_len:
                raise AgoInputError(self.option, f"phrase {phrase!r} has {len(ids)} tokens, more than the "
                                    f"detector's text length {self.max_text_len} allows")
            pieces.append((k, ids))
        dot = self.tokenizer.convert_tokens_to_ids(".")
        passes, current = [], None
        for k, ids in pieces:
            if current is None or len(current["ids"]) + len(ids) + 2 > self.max_text_len:   # + "." + [SEP]
                current = {"ids": [self.tokenizer.cls_token_id], "spans": []}
                passes.append(current)
            start = len(current["ids"])
            current["ids"] += ids + [dot]
            current["spans"].append((k, start, start + len(ids)))
        import torch

        return [{"input_ids": torch.tensor([p["ids"] + [self.tokenizer.sep_token_id]], dtype=torch.long),
                 "spans": p["spans"]} for p in passes]

    def detect(self, image_rgb: np.ndarray, config: GroundedSamConfig) -> Detections:
        import torch

        H, W = image_rgb.shape[:2]
        h, w = detector_resize(H, W, self.shortest, self.longest)
        pixels = to_tensor(image_rgb, w, h, self.mean, self.std, self.device)
        boxes, scores, phrases = [], [], []
        with torch.inference_mode():
            for p in self.passes:
                ids = p["input_ids"].to(self.device)
                out = self.model(pixel_values=pixels, input_ids=ids, attention_mask=torch.ones_like(ids),
                                 token_type_ids=torch.zeros_like(ids), pixel_mask=torch.ones(1, h, w, dtype=torch.long,
                                                                                         device=self.device))
                prob = out.logits[0, :, : ids.shape[1]].sigmoid().float().cpu().numpy()   # (Q, T)
                span_prob = np.stack([prob[:, a:b].max(axis=1) for _, a, b in p["spans"]], axis=1)   # (Q, P)
                best = span_prob.argmax(axis=1)
                score = prob.max(axis=1)
                keep = (score > config.box_threshold) & (span_prob[np.arange(len(best)), best] > config.text_threshold)
                if not keep.any():
                    continue
                cx, cy, bw, bh = out.pred_boxes[0].float().cpu().numpy()[keep].T
                xyxy = np.stack([(cx - bw / 2) * W, (cy - bh / 2) * H, (cx + bw / 2) * W, (cy + bh / 2) * H], axis=1)
                boxes.append(np.clip(xyxy, 0, [W, H, W, H]).astype(np.float32))
                scores.append(score[keep].astype(np.float32))
                phrases.append(np.asarray([p["spans"][j][0] for j in best[keep]], dtype=np.int64))
        if not boxes:
            return Detections(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))
        boxes, scores, phrases = np.concatenate(boxes), np.concatenate(scores), np.concatenate(phrases)
        ok = (boxes[:, 2] - boxes[:, 0] >= 1) & (boxes[:, 3] - boxes[:, 1] >= 1)
        boxes, scores, phrases = boxes[ok], scores[ok], phrases[ok]
        keep = nms(boxes, scores, config.nms_iou)[: config.max_boxes]
        return Detections(boxes[keep], scores[keep], phrases[keep])


class BoxSegmenterSam:
    """SAM (`--sam DIR`): one image embedding, one mask per box."""

    option = "--sam"

    def __init__(self, folder: str | Path, device, model=None):
        quiet_transformers()
        from transformers import SamModel

        self.folder = Path(folder)
        self.model = model if model is not None else load_model(SamModel, folder, self.option, "sam", device)
        self.device = device
        size = self.model.config.vision_config.image_size
        self.size = int(size if isinstance(size, int) else size[0])   # the input SAM's position embeddings fit
        self.mean, self.std = mean_std(preprocessor_config(folder) if model is None else {}, IMAGENET_MEAN,
                                       IMAGENET_STD, self.folder / "preprocessor_config.json")

    def masks(self, image_rgb: np.ndarray, boxes: np.ndarray, batch: int = 16):
        """Yield (box index, (H, W) bool mask) for each box, in the order given."""
        import torch
        import torch.nn.functional as F

        H, W = image_rgb.shape[:2]
        scale = self.size / max(H, W)
        h, w = int(H * scale + 0.5), int(W * scale + 0.5)
        pixels = torch.zeros(1, 3, self.size, self.size, device=self.device)
        pixels[:, :, :h, :w] = to_tensor(image_rgb, w, h, self.mean, self.std, self.device)
        with torch.inference_mode():
            emb = self.model.get_image_embeddings(pixels)
            sx, sy = w / W, h / H
            for s in range(0, len(boxes), batch):
                b = torch.as_tensor(boxes[s: s + batch] * np.float32([sx, sy, sx, sy]), device=self.device)[None]
                out = self.model(image_embeddings=emb, input_boxes=b, multimask_output=False)
                low = out.pred_masks[0, :, 0].float()                    # (n, 256, 256) logits
                up = F.interpolate(low[:, None], (self.size, self.size), mode="bilinear", align_corners=False)
                up = up[:, :, :h, :w]
                for j in range(up.shape[0]):
                    full = F.interpolate(up[j: j + 1], (H, W), mode="bilinear", align_corners=False)
                    yield s + j, (full[0, 0] > 0).cpu().numpy()


class GroundedSam:
    """Label maps of phrase ids (k + 1 = phrase k of `phrases`; 0 = no label) for camera images."""

    def __init__(self, detector: str | Path | PhraseDetector, sam: str | Path | BoxSegmenterSam, phrases: list[str],
                 config: GroundedSamConfig, device):
        config.check()
        if len(phrases) > MAX_PHRASES:
            raise AgoInputError("--prompts", f"{len(phrases)} phrases; label-map files hold at most {MAX_PHRASES}")
        self.config = config
        self.detector = detector if isinstance(detector, PhraseDetector) else PhraseDetector(detector, phrases, device)
        self.sam = sam if isinstance(sam, BoxSegmenterSam) else BoxSegmenterSam(sam, device)

    @property
    def num_passes(self) -> int:
        return len(self.detector.passes)

    def label_map(self, image_rgb: np.ndarray) -> np.ndarray:
        H, W = image_rgb.shape[:2]
        det = self.detector.detect(image_rgb, self.config)
        label = np.zeros((H, W), dtype=np.uint8)
        order = np.lexsort((-np.arange(len(det.scores)), det.scores))   # lowest score first, highest painted last
        for j, mask in self.sam.masks(image_rgb, det.boxes[order]):
            label[mask] = det.phrases[order[j]] + 1
        return label
