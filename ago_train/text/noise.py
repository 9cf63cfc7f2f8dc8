"""Noise prompts: random dictionary nouns used as negative text embeddings in grounding training.

The AGO paper draws N_noise = 100 random words per training step from an NLTK dictionary and
encodes them with the prompt encoder. Here the dictionary is built once from WordNet nouns
(`nltk.corpus.wordnet`, data set up by scripts/setup_nltk_data.sh), filtered, encoded and cached
as a small .npz (float16 embeddings), so a training step only samples rows:

    bank = NoiseBank.load(ensure_noise_bank())
    neg = bank.sample(100, rng)        # float32 (100, 384), L2-normalised rows

The bank is made by one text encoder and records it (meta encoder_id): MiniLM by default; a CLIP folder's
tower (`ago prompts noise --text-encoder DIR`, `ago train --text-encoder DIR`) makes its own, cached under
its encoder id. Training refuses a noise bank of another encoder than its prompt bank (`training_noise_bank`).

Filters, in order (counts measured in docs/prompts.md):
1. single words: letters only, 3..15 characters (drops multiword lemmas, hyphenated and
   numeric ones);
2. a lowercase entry of the `words` corpus (Webster's 2nd, /usr/share/dict/web2): a real
   dictionary word and not only a proper noun (web2 capitalises those: "Aaron", "Aberdeen");
3. one token of the encoder's vocabulary (a WordPiece of MiniLM, a BPE token of CLIP): the encoder knows
   the word as a whole (rare words split into pieces get embeddings dominated by sub-word fragments);
4. not a label word: not a word of any phrase or class name of the shipped prompt files;
5. not a near-synonym: cosine to every label phrase of the shipped prompt files <= 0.5
   (NEAR_SYNONYM_COS; chosen by inspecting the words per cosine band, docs/prompts.md);
6. at most MAX_WORDS words, a deterministic sample (seed 0) when more survive.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ago_runtime.atomic import save_npz
from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.prompts import PROMPTS_DIR, parse_prompt_file
from ago_runtime.cache import ago_cache_dir
from ago_runtime.vocab.text_encoder import MINILM_ID

REPO_ROOT = Path(__file__).resolve().parents[2]
NEAR_SYNONYM_COS = 0.5
MAX_WORDS = 6000
SEED = 0
FORMAT_VERSION = 1
# Bump when the filters change: ensure_noise_bank rebuilds banks made by an older recipe.
RECIPE_VERSION = 2
SETUP_HINT = "run scripts/setup_nltk_data.sh (WordNet from Debian packages into <repo>/.nltk_data)"


def default_noise_bank_path(encoder_id: str = MINILM_ID) -> Path:
    """The cached noise bank of the encoder `encoder_id` (MiniLM's, or "clip:<hex>" -> noise_bank-clip_<hex>.npz)."""
    name = re.sub(r"[^\w.-]+", "_", encoder_id)
    return ago_cache_dir() / "noise" / f"noise_bank-{name}.npz"


def _nltk():
    """nltk with <repo>/.nltk_data on its search path (after $NLTK_DATA)."""
    import nltk

    local = str(REPO_ROOT / ".nltk_data")
    if local not in nltk.data.path:
        nltk.data.path.append(local)
    return nltk


def label_phrases(prompt_files: list[Path] | None = None) -> list[str]:
    """Every phrase and class name (underscores as spaces) of the given / all shipped prompt files."""
    files = prompt_files if prompt_files is not None else sorted(PROMPTS_DIR.glob("*.txt"))
    out: dict[str, None] = {}
    for f in files:
        space = parse_prompt_file(f)
        for c in space.classes:
            out[c.name.replace("_", " ").lower()] = None
            for p in c.phrases:
                out[p.lower()] = None
    return list(out)


@dataclass
class NoiseFilterReport:
    """How many words survive each filter (in order)."""

    counts: dict[str, int] = field(default_factory=dict)


def candidate_words(tokenizer, labels: list[str], report: NoiseFilterReport | None = None) -> list[str]:
    """Filters 1-4 of the module docstring, sorted words. Raises AgoInputError without WordNet data."""
    nltk = _nltk()
    try:
        from nltk.corpus import wordnet, words

        lemmas = set(wordnet.all_lemma_names(pos="n"))     # lowercased by nltk
        # web2 keeps case: proper nouns are capitalised there ("Aaron", "Aberdeen").
        dictionary = set(words.words("en"))
    except LookupError:
        raise AgoInputError(None, f"NLTK WordNet / words data not found (searched {nltk.data.path}): "
                            f"{SETUP_HINT}") from None
    report = report if report is not None else NoiseFilterReport()
    report.counts["wordnet noun lemmas"] = len(lemmas)
    kept = [w for w in lemmas if re.fullmatch(r"[a-z]{3,15}", w)]
    report.counts["single lowercase word, 3-15 letters"] = len(kept)
    kept = [w for w in kept if w in dictionary]
    report.counts["lowercase entry of the words corpus (web2)"] = len(kept)
    kept = [w for w in kept if len(tokenizer.tokenize_ids(w)) == 1]
    report.counts["one token of the encoder's vocabulary"] = len(kept)
    label_words = {w for p in labels for w in [p, *p.split()]}
    kept = sorted(w for w in kept if w not in label_words)
    report.counts["not a label word"] = len(kept)
    return kept


@dataclass
class NoiseBank:
    words: list[str]
    embeddings: np.ndarray     # float16 (N, C), L2-normalised rows
    meta: dict = field(default_factory=dict)

    @property
    def dim(self) -> int:
        return int(self.embeddings.shape[1])

    def __len__(self) -> int:
        return len(self.words)

    def sample_indices(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n distinct row indices (with replacement only if n > number of words)."""
        return rng.choice(len(self.words), size=n, replace=n > len(self.words))

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """float32 (n, C): embeddings of n random noise words (deterministic for a seeded rng)."""
        return self.embeddings[self.sample_indices(n, rng)].astype(np.float32)

    def save(self, path: str | Path) -> Path:
        save_npz(path, words=np.array(self.words, dtype=str), embeddings=self.embeddings.astype(np.float16),
                 meta=np.array([json.dumps({**self.meta, "format_version": FORMAT_VERSION})]))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "NoiseBank":
        path = Path(path)
        from ago_runtime.readers import open_npz

        if not path.is_file():
            raise AgoInputError(path, "noise bank not found (build it with `ago prompts noise`)")
        with open_npz(path, "noise bank file") as z:
            words = [str(w) for w in z["words"].tolist()]
            emb = z["embeddings"]
            try:
                meta = json.loads(str(z["meta"].reshape(-1)[0]))
            except (ValueError, IndexError):
                raise AgoInputError(path, "noise bank metadata is not valid JSON") from None
        if meta.get("format_version") != FORMAT_VERSION or emb.ndim != 2 or emb.shape[0] != len(words):
            raise AgoInputError(path, "noise bank has the wrong format; rebuild with `ago prompts noise --force`")
        return cls(words, emb, meta)


def build_noise_bank(encoder=None, labels: list[str] | None = None, threshold: float = NEAR_SYNONYM_COS,
                     max_words: int = MAX_WORDS, seed: int = SEED, candidates: list[str] | None = None,
                     max_candidates: int | None = None) -> NoiseBank:
    """Filter the WordNet nouns (module docstring) and encode the survivors with `encoder`
    (default: the torch MiniLM, fp32).

    `candidates` replaces filters 1-3 (WordNet lookup) by a given word list; `max_candidates`
    subsamples the candidates (seeded) before encoding - both for quick tests.
    """
    if encoder is None:
        from .minilm import TorchMiniLMEncoder

        encoder = TorchMiniLMEncoder(batch_size=256)
    labels = labels if labels is not None else label_phrases()
    report = NoiseFilterReport()
    if candidates is None:
        words = candidate_words(encoder.tokenizer, labels, report)
    else:
        label_words = {w for p in labels for w in [p, *p.split()]}
        words = sorted({w for w in candidates if w not in label_words})
        report.counts["given candidates, not a label word"] = len(words)
    if max_candidates is not None and len(words) > max_candidates:
        keep = np.sort(np.random.default_rng(seed).choice(len(words), size=max_candidates, replace=False))
        words = [words[i] for i in keep]
        report.counts[f"subsampled to {max_candidates} candidates"] = len(words)
    label_emb = encoder.encode(labels)
    emb = encoder.encode(words) if words else np.zeros((0, label_emb.shape[1]), np.float32)
    near = (emb @ label_emb.T).max(axis=1) > threshold
    words = [w for w, drop in zip(words, near) if not drop]
    emb = emb[~near]
    report.counts[f"cosine to every label phrase <= {threshold}"] = len(words)
    if not words:
        raise AgoInputError(None, f"no noise word is left after the filters ({report.counts}) with the text encoder "
                            f"{encoder.encoder_id}")
    if len(words) > max_words:
        keep = np.sort(np.random.default_rng(seed).choice(len(words), size=max_words, replace=False))
        words = [words[i] for i in keep]
        emb = emb[keep]
    report.counts[f"capped at {max_words} (seed {seed})"] = len(words)
    meta = {"recipe_version": RECIPE_VERSION, "encoder_id": encoder.encoder_id, "encoder_variant": encoder.variant,
            "encoder_hash": encoder.weights_hash, "threshold": threshold, "max_words": max_words,
            "seed": seed, "filter_counts": report.counts, "num_label_phrases": len(labels)}
    return NoiseBank(words, emb.astype(np.float16), meta)


def _up_to_date(path: Path, encoder_id: str) -> bool:
    """A readable noise bank at `path` made by the current filter recipe and the encoder `encoder_id`."""
    if not path.is_file():
        return False
    try:
        meta = NoiseBank.load(path).meta
    except AgoInputError:
        return False   # damaged or foreign: rebuilt
    return meta.get("recipe_version") == RECIPE_VERSION and meta.get("encoder_id", MINILM_ID) == encoder_id


def ensure_noise_bank(path: str | Path | None = None, force: bool = False, encoder=None) -> Path:
    """Path of the noise bank of `encoder` (default: the torch MiniLM); builds it first if it is missing, made by an
    older filter recipe or another encoder, unreadable, or `force`. Default path: default_noise_bank_path(its id)."""
    encoder_id = encoder.encoder_id if encoder is not None else MINILM_ID
    path = Path(path) if path is not None else default_noise_bank_path(encoder_id)
    if force or not _up_to_date(path, encoder_id):
        build_noise_bank(encoder).save(path)
    return path


def training_noise_bank(path: str | None, text_encoder: str | None, encoder_id: str, width: int) -> NoiseBank:
    """The noise bank a training run samples from: `path` (the config's noise_bank) when given, else the cached one of
    the run's text encoder (`text_encoder`: a CLIP folder, None = MiniLM), built when missing. Refused with one line
    naming both when its encoder or width is not the prompt bank's (`encoder_id`, `width`: its encoder and width)."""
    from ago_runtime.vocab.model_folder import check_same_encoder, clip_encoder_id

    if path is None:
        run_encoder = clip_encoder_id(text_encoder) if text_encoder is not None else MINILM_ID
        path = default_noise_bank_path(run_encoder)
        if not _up_to_date(path, run_encoder):
            encoder = None
            if text_encoder is not None:
                from .clip import TorchClipTextEncoder

                encoder = TorchClipTextEncoder(text_encoder, "text_encoder", batch_size=256)
            ensure_noise_bank(path, encoder=encoder)
    nb = NoiseBank.load(path)
    check_same_encoder("the noise words", str(nb.meta.get("encoder_id", MINILM_ID)), "the prompt bank",
                       str(encoder_id), source=path)
    if nb.dim != width:
        raise AgoInputError(path, f"noise words are {nb.dim}-d, the prompt bank's embeddings {width}-d")
    return nb
