"""Prompt banks: the text embeddings of a label space's phrases, saved as one .npz file.

A PromptBank holds embeddings (P, C) float32 of the P phrases of a label space (phrase i belongs
to class phrase_class[i]), the class names, known set and Occ3D ids, and which encoder (id,
variant, sha256 of its weights file) and template made them. Class score = max over the class's
phrases: `class_scores(phrase_scores)` (the rule of ago_runtime.vocab.phrase_layout, as the voxel decision's).

Compatibility rule: a bank fits a model when encoder_id and dim match the model's; the variant
(torch fp32, ONNX fp32, ONNX int8) does not matter (they agree to cosine >= 0.999, measured in
docs/prompts.md). Anything else is refused, with a clear message, by the one check of a bank against a
bundle, ago_runtime.predict.contract.check_bank_fits.

File format (np.load(..., allow_pickle=False) only): arrays `embeddings` float32 (P, C),
`phrases` and `class_names` fixed-width unicode, `phrase_class` int64 (P,), and `meta`, a
one-element unicode array holding JSON with the other fields.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ago_runtime.atomic import save_npz
from ago_runtime.classes import OCC3D_NUSCENES, ClassTable, table_from_ref, table_record
from ago_runtime.errors import AgoInputError
from ago_runtime.readers import open_npz
from ago_runtime.vocab.phrase_layout import PhraseLayout
from ago_runtime.vocab.prompts import LabelSpace, parse_prompt_file

FORMAT_VERSION = 1
# The default prompt template ("{}" = the plain phrase): chosen by benchmarks/prompt_templates.py,
# see benchmarks/results/prompt_templates.md.
DEFAULT_TEMPLATE = "{}"


def apply_template(template: str, phrase: str) -> str:
    return template.replace("{}", phrase)


def check_template(template: str, option: str | None = "template") -> str:
    """`template` when it has exactly one `{}` and is a short line of text; AgoInputError naming `option`."""
    if template.count("{}") != 1:
        raise AgoInputError(option, f"{template[:80]!r} must contain exactly one '{{}}' for the phrase")
    if len(template) > 200 or any(ord(c) < 32 for c in template):
        raise AgoInputError(option, "must be one short line of text (at most 200 characters, no control characters)")
    return template


@dataclass
class PromptBank:
    embeddings: np.ndarray          # float32 (P, C)
    phrases: list[str]
    class_names: list[str]
    phrase_class: np.ndarray        # int64 (P,), values 0..K-1, every class has >= 1 phrase
    encoder_id: str
    encoder_variant: str
    encoder_hash: str
    dim: int
    normalised: bool = True
    template: str = DEFAULT_TEMPLATE
    source_hash: str = ""           # sha256 of the prompt file bytes
    label_space: str = ""
    known: list[str] = field(default_factory=list)
    occ3d_ids: list[tuple[int, ...]] = field(default_factory=list)   # per class, ids in `class_table`
    format_version: int = FORMAT_VERSION
    class_table: ClassTable = OCC3D_NUSCENES   # the label table occ3d_ids index (ago_runtime.classes)

    def __post_init__(self):
        self.embeddings = np.asarray(self.embeddings, dtype=np.float32)
        self.phrase_class = np.asarray(self.phrase_class, dtype=np.int64)
        self.phrases = [str(p) for p in self.phrases]
        self.class_names = [str(c) for c in self.class_names]
        self.occ3d_ids = [tuple(int(i) for i in ids) for ids in self.occ3d_ids] or [() for _ in self.class_names]
        self._validate(None)

    def _validate(self, path) -> None:
        p, k = len(self.phrases), len(self.class_names)
        if self.embeddings.ndim != 2 or self.embeddings.shape != (p, self.dim):
            raise AgoInputError(path, f"embeddings have shape {self.embeddings.shape}, expected ({p}, {self.dim})")
        if self.phrase_class.shape != (p,):
            raise AgoInputError(path, f"phrase_class has shape {self.phrase_class.shape}, expected ({p},)")
        if p and (self.phrase_class.min() < 0 or self.phrase_class.max() >= k):
            raise AgoInputError(path, "phrase_class has indices outside the class list")
        if set(np.unique(self.phrase_class).tolist()) != set(range(k)):
            raise AgoInputError(path, "some class has no phrase")
        if len(self.occ3d_ids) != k:
            raise AgoInputError(path, f"occ3d_ids has {len(self.occ3d_ids)} entries for {k} classes")
        strange = sorted({i for ids in self.occ3d_ids for i in ids} - set(self.class_table.ids))
        if strange:
            raise AgoInputError(path, f"occ3d_ids {strange[:8]} are not ids of its class table {self.class_table.name}")
        if not np.isfinite(self.embeddings).all():
            raise AgoInputError(path, "embeddings contain NaN or inf")
        self._layout = PhraseLayout(self.phrase_class, k)   # phrases by class, for class_scores

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    @property
    def num_phrases(self) -> int:
        return len(self.phrases)

    def known_mask(self) -> np.ndarray:
        return np.array([c in set(self.known) for c in self.class_names], dtype=bool)

    def class_scores(self, phrase_scores: np.ndarray) -> np.ndarray:
        """(..., P) per-phrase scores -> (..., K) per-class scores = max over each class's phrases."""
        s = np.asarray(phrase_scores)
        if s.shape[-1] != self.num_phrases:
            raise ValueError(f"last axis has {s.shape[-1]} scores, the bank has {self.num_phrases} phrases")
        s = np.moveaxis(s, -1, 0)
        if not self._layout.in_order:
            s = s[self._layout.order]
        return np.moveaxis(self._layout.class_max(s), 0, -1)

    def class_similarity(self) -> np.ndarray:
        """(K, K) max cosine over phrase pairs of two classes (diagonal: max over distinct phrases, 1 if one)."""
        e = self.embeddings / np.maximum(np.linalg.norm(self.embeddings, axis=1, keepdims=True), 1e-12)
        sim = e @ e.T
        np.fill_diagonal(sim, -np.inf)
        by_class = self.class_scores(sim)                       # (P, K)
        out = self.class_scores(by_class.T)                      # (K, K)
        single = np.bincount(self.phrase_class, minlength=self.num_classes) == 1
        out[single, single] = 1.0
        return out

    # ---- files ---------------------------------------------------------------------------
    def meta(self) -> dict:
        return {"format_version": self.format_version, "encoder_id": self.encoder_id,
                "encoder_variant": self.encoder_variant, "encoder_hash": self.encoder_hash,
                "dim": int(self.dim), "normalised": bool(self.normalised), "template": self.template,
                "source_hash": self.source_hash, "label_space": self.label_space,
                "known": list(self.known), "occ3d_ids": [list(t) for t in self.occ3d_ids],
                **table_record(self.class_table)}

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        save_npz(path, embeddings=self.embeddings, phrases=np.array(self.phrases, dtype=str),
                 class_names=np.array(self.class_names, dtype=str), phrase_class=self.phrase_class,
                 meta=np.array([json.dumps(self.meta())]))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "PromptBank":
        path = Path(path)
        with open_npz(path, "prompt bank (.npz) file") as z:
            arrays = {k: z[k] for k in z.files}
        need = {"embeddings", "phrases", "class_names", "phrase_class", "meta"}
        if not need <= set(arrays):
            raise AgoInputError(path, f"not a prompt bank: missing arrays {sorted(need - set(arrays))}")
        try:
            meta = json.loads(str(arrays["meta"].reshape(-1)[0]))
        except (ValueError, IndexError):
            raise AgoInputError(path, "prompt bank metadata is not valid JSON") from None
        if meta.get("format_version") != FORMAT_VERSION:
            raise AgoInputError(path, f"prompt bank format version {meta.get('format_version')!r}, "
                                f"this ago reads version {FORMAT_VERSION}; rebuild it with `ago prompts build`")
        if arrays["embeddings"].dtype != np.float32 or arrays["phrase_class"].dtype != np.int64:
            raise AgoInputError(path, "prompt bank arrays have the wrong dtypes")
        try:
            bank = cls.__new__(cls)
            bank.embeddings = arrays["embeddings"]
            bank.phrases = [str(p) for p in arrays["phrases"].tolist()]
            bank.class_names = [str(c) for c in arrays["class_names"].tolist()]
            bank.phrase_class = arrays["phrase_class"]
            bank.encoder_id = str(meta["encoder_id"])
            bank.encoder_variant = str(meta["encoder_variant"])
            bank.encoder_hash = str(meta["encoder_hash"])
            bank.dim = int(meta["dim"])
            bank.normalised = bool(meta["normalised"])
            bank.template = str(meta["template"])
            bank.source_hash = str(meta["source_hash"])
            bank.label_space = str(meta["label_space"])
            bank.known = [str(k) for k in meta["known"]]
            bank.occ3d_ids = [tuple(int(i) for i in ids) for ids in meta["occ3d_ids"]]
            bank.format_version = FORMAT_VERSION
            bank.class_table = table_from_ref(meta.get("class_table", "occ3d_nuscenes"), path)
        except (KeyError, TypeError, ValueError) as e:
            raise AgoInputError(path, f"prompt bank metadata incomplete: {e}") from None
        bank._validate(path)
        zero = np.abs(bank.embeddings).max(axis=1) == 0 if bank.num_phrases else np.zeros(0, bool)
        if zero.any():   # a file's phrase with no direction scores nothing (a hand-made or damaged bank)
            raise AgoInputError(path, f"the embedding of phrase {bank.phrases[int(np.argmax(zero))]!r} is all zeros")
        return bank


MAX_INFER_CLASSES = 254   # `ago infer` writes uint8 semantics with free = K, so K + 1 <= 255


def check_class_count(num_classes: int, source) -> None:
    """Refuse (naming `source`, a prompt file or bank) more classes than `ago infer` can write."""
    if num_classes > MAX_INFER_CLASSES:
        raise AgoInputError(source, f"{num_classes} classes: `ago infer` predicts at most {MAX_INFER_CLASSES} "
                            "(uint8 semantics with free = K); split the prompt file")


def build_bank(label_space: LabelSpace, encoder, template: str = DEFAULT_TEMPLATE) -> PromptBank:
    """Encode every phrase of `label_space` (after `template`) with `encoder`.

    `encoder`: anything with encode(list[str]) -> (N, C) array and attributes encoder_id,
    variant, dim, weights_hash (OnnxTextEncoder, ago_train's TorchMiniLMEncoder).
    """
    check_template(template)
    phrases = label_space.phrases
    emb = np.asarray(encoder.encode([apply_template(template, p) for p in phrases]), dtype=np.float32)
    norms = np.linalg.norm(emb, axis=1)
    return PromptBank(
        embeddings=emb, phrases=phrases, class_names=label_space.class_names,
        phrase_class=label_space.phrase_class, encoder_id=encoder.encoder_id,
        encoder_variant=encoder.variant, encoder_hash=encoder.weights_hash, dim=int(emb.shape[1]),
        normalised=bool(np.allclose(norms, 1.0, atol=1e-3)), template=template,
        source_hash=label_space.sha256, label_space=label_space.name,
        known=[c for c in label_space.class_names if c in label_space.known],
        occ3d_ids=[c.occ3d_ids for c in label_space.classes], class_table=label_space.class_table)


def bank_cache_key(source_hash: str, encoder_hash: str, template: str) -> str:
    text = f"{FORMAT_VERSION}|{source_hash}|{encoder_hash}|{template}"
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def load_prompt_bank(prompts: "str | Path | LabelSpace", encoder=None, cache_dir: str | Path | None = None,
                     template: str = DEFAULT_TEMPLATE, *, bundle=None) -> PromptBank:
    """The one way a prompt file becomes a PromptBank (infer, demo, retrieve, training, pseudo-labels, export):

        prompt file --parse_prompt_file--> LabelSpace --(content hash)--> cached bank --> PromptBank

    1. `prompts`: a prompt file (a path, or a shipped name: "cw" -> prompts/cw.txt), read and checked
       once by `parse_prompt_file`; or a LabelSpace already parsed (e.g. a checkpoint's).
    2. With `bundle` (a predict.Bundle, as `ago infer` passes it): more classes than `ago infer` can
       write are refused before any encoding; a bank the bundle ships for this same prompt text (same
       name and sha256) is used as it is; `encoder` defaults to the one that fits the bundle
       (`bundle_text_encoder`).
    3. The cache: `cache_dir` (default ~/.cache/ago/banks, $AGO_CACHE_DIR/banks), file
       `<label space>-<key>.npz`, key = hash of (bank format, prompt file sha256, encoder weights sha256,
       template); a damaged entry, or one whose class table is not the prompt file's, is rebuilt.
    4. Otherwise `build_bank` encodes the phrases with `encoder` (default: default_text_encoder()) and
       the bank is saved in the cache.
    """
    from ago_runtime.cache import ago_cache_dir
    from ago_runtime.vocab.text_encoder import bundle_text_encoder, default_text_encoder

    space = prompts if isinstance(prompts, LabelSpace) else parse_prompt_file(prompts)
    if bundle is not None:
        check_class_count(space.num_classes, space.source)       # before any encoding
        stem = space.source.stem if space.source is not None else space.name
        if stem in bundle.banks:   # a shipped prompt file the bundle pre-built: check it is the same text
            shipped = bundle.load_bank(stem)
            if shipped.source_hash == space.sha256 and shipped.class_table == space.class_table:
                return shipped
        encoder = encoder if encoder is not None else bundle_text_encoder(bundle)
    encoder = encoder if encoder is not None else default_text_encoder()
    if not space.sha256:   # not from a file: nothing to key a cache entry by
        return build_bank(space, encoder, template)
    cache_dir = Path(cache_dir) if cache_dir is not None else ago_cache_dir() / "banks"
    stem = re.sub(r"[^\w.-]+", "_", space.name) or "prompts"
    path = cache_dir / f"{stem}-{bank_cache_key(space.sha256, encoder.weights_hash, template)}.npz"
    if path.is_file():
        try:
            cached = PromptBank.load(path)
            if cached.class_table == space.class_table:   # (entries made before banks recorded their table are rebuilt)
                return cached
        except AgoInputError:
            pass  # a damaged cache entry is rebuilt below
    bank = build_bank(space, encoder, template)
    bank.save(path)
    return bank
