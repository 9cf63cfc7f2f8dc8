"""BERT WordPiece tokenizer in pure Python + numpy (no torch, no `tokenizers` package).

Takes a BERT `vocab.txt` (one token per line, line number = id) and text; gives int64 arrays
`input_ids` and `attention_mask` of shape (batch, seq_len), padded with [PAD]=0 to the longest
item of the batch, each item `[CLS] tokens... [SEP]`, truncated to `max_length` tokens in all.

Steps (the same as Hugging Face's BertNormalizer + BertPreTokenizer + WordPiece, uncased):
1. clean: drop NUL / U+FFFD / control characters, turn any whitespace into a space;
2. put spaces around CJK ideographs (each becomes its own word);
3. strip accents (NFD, drop combining marks), then lowercase;
4. split on whitespace and on every punctuation character (each punctuation char is a word);
5. WordPiece each word: greedy longest match from the left, continuation pieces prefixed "##";
   a word with no full match (or longer than 100 chars) becomes [UNK].
"""

from __future__ import annotations

import unicodedata
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError

MAX_CHARS_PER_WORD = 100


def _is_whitespace(ch: str) -> bool:
    return ch.isspace()


def _is_control(ch: str) -> bool:
    if ch in ("\t", "\n", "\r"):
        return False
    return unicodedata.category(ch) in ("Cc", "Cf", "Cn", "Co", "Cs")


def _is_punctuation(ch: str) -> bool:
    cp = ord(ch)
    # ASCII symbols count as punctuation for BERT even where Unicode says "Symbol" ($, +, ^, `...).
    if 33 <= cp <= 47 or 58 <= cp <= 64 or 91 <= cp <= 96 or 123 <= cp <= 126:
        return True
    return unicodedata.category(ch).startswith("P")


def _is_cjk(cp: int) -> bool:
    return (0x4E00 <= cp <= 0x9FFF or 0x3400 <= cp <= 0x4DBF or 0x20000 <= cp <= 0x2A6DF
            or 0x2A700 <= cp <= 0x2B73F or 0x2B740 <= cp <= 0x2B81F or 0x2B820 <= cp <= 0x2CEAF
            or 0xF900 <= cp <= 0xFAFF or 0x2F800 <= cp <= 0x2FA1F)


def basic_tokenize(text: str) -> list[str]:
    """Normalise `text` and split it into words and single punctuation characters."""
    chars = []
    for ch in text:
        cp = ord(ch)
        if cp == 0 or cp == 0xFFFD or _is_control(ch):
            continue
        if _is_whitespace(ch):
            chars.append(" ")
        elif _is_cjk(cp):
            chars.extend((" ", ch, " "))
        else:
            chars.append(ch)
    text = "".join(chars)
    text = "".join(c for c in unicodedata.normalize("NFD", text) if unicodedata.category(c) != "Mn")
    text = text.lower()
    words: list[str] = []
    for chunk in text.split():
        current = []
        for ch in chunk:
            if _is_punctuation(ch):
                if current:
                    words.append("".join(current))
                    current = []
                words.append(ch)
            else:
                current.append(ch)
        if current:
            words.append("".join(current))
    return words


class WordPieceTokenizer:
    """Uncased BERT tokenizer over a vocab.txt. `encode(texts)` -> (input_ids, attention_mask)."""

    def __init__(self, vocab_path: str | Path, max_length: int = 256, unk_token: str = "[UNK]",
                 cls_token: str = "[CLS]", sep_token: str = "[SEP]", pad_token: str = "[PAD]"):
        self.vocab_path = Path(vocab_path)
        try:
            lines = self.vocab_path.read_text(encoding="utf-8").split("\n")
        except (OSError, UnicodeDecodeError) as e:
            raise AgoInputError(vocab_path, f"cannot read the vocabulary: {e}") from None
        if lines and lines[-1] == "":
            lines = lines[:-1]
        self.vocab = {tok: i for i, tok in enumerate(lines)}
        for tok in (unk_token, cls_token, sep_token, pad_token):
            if tok not in self.vocab:
                raise AgoInputError(vocab_path, f"vocabulary has no {tok} token; is this a BERT vocab.txt?")
        if max_length < 3:
            raise ValueError("max_length must leave room for [CLS], a token and [SEP]")
        self.max_length = int(max_length)
        self.unk_id = self.vocab[unk_token]
        self.cls_id = self.vocab[cls_token]
        self.sep_id = self.vocab[sep_token]
        self.pad_id = self.vocab[pad_token]
        self._wordpiece = lru_cache(maxsize=65536)(self._wordpiece_uncached)

    def _wordpiece_uncached(self, word: str) -> tuple[int, ...]:
        if len(word) > MAX_CHARS_PER_WORD:
            return (self.unk_id,)
        ids = []
        start = 0
        while start < len(word):
            end = len(word)
            found = None
            while start < end:
                piece = word[start:end] if start == 0 else "##" + word[start:end]
                if piece in self.vocab:
                    found = self.vocab[piece]
                    break
                end -= 1
            if found is None:
                return (self.unk_id,)
            ids.append(found)
            start = end
        return tuple(ids)

    def tokenize_ids(self, text: str) -> list[int]:
        """Word-piece ids of `text`, without [CLS]/[SEP] and without truncation."""
        ids: list[int] = []
        for word in basic_tokenize(text):
            ids.extend(self._wordpiece(word))
        return ids

    def tokens(self, text: str) -> list[str]:
        """The word-piece strings of `text` (for display and tests)."""
        inv = {i: t for t, i in self.vocab.items()}
        return [inv[i] for i in self.tokenize_ids(text)]

    def encode_one(self, text: str) -> list[int]:
        """[CLS] ids [SEP], truncated (with a warning) to max_length tokens."""
        return wrap_ids(self.tokenize_ids(text), self.cls_id, self.sep_id, self.max_length, text, "word pieces")

    def encode(self, texts: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """(input_ids, attention_mask), both int64 (B, L) with L = the longest item, right-padded."""
        if isinstance(texts, str):
            raise TypeError("encode takes a list of strings")
        return pad_batch([self.encode_one(t) for t in texts], self.pad_id)


def wrap_ids(ids: list[int], start_id: int, end_id: int, max_length: int, text: str, unit: str) -> list[int]:
    """start ids end, the ids cut (with a warning naming `unit`) so that the whole is at most max_length tokens."""
    room = max_length - 2
    if len(ids) > room:
        warnings.warn(f"text of {len(ids)} {unit} truncated to {room} (encoder limit {max_length} tokens): "
                      f"{text[:60]!r}...", stacklevel=4)
        ids = ids[:room]
    return [start_id, *ids, end_id]


def pad_batch(rows: list[list[int]], pad_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(input_ids, attention_mask), both int64 (B, L) with L = the longest row (2 when there is none), the rows
    right-padded with `pad_id` (mask 0)."""
    length = max((len(r) for r in rows), default=2)
    ids = np.full((len(rows), length), pad_id, dtype=np.int64)
    mask = np.zeros((len(rows), length), dtype=np.int64)
    for i, r in enumerate(rows):
        ids[i, : len(r)] = r
        mask[i, : len(r)] = 1
    return ids, mask
