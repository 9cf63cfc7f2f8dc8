"""CLIP's byte-level BPE tokenizer, read from a Hugging Face `tokenizer.json` with the `tokenizers` library.

Takes a `tokenizer.json` (what `CLIPTokenizer.save_pretrained` writes: normalizer, pre-tokenizer, BPE vocab and
merges, and a post-processor that wraps a text in its start and end tokens) and texts; gives int64 arrays
`input_ids` and `attention_mask` (batch, seq_len), the same interface as `WordPieceTokenizer`:

    <|startoftext|> tokens... <|endoftext|>   then padding, right, with the end token (mask 0)

* The start and end ids are read from the file itself: the ids its post-processor puts around an empty text.
* Padding with the end token is what CLIP's own tokenizer does (`pad_token` = `<|endoftext|>`), and it keeps
  both of CLIP's pooling rules right: the first end token (`eos_token_id`) and the largest id (argmax of the
  ids, the original CLIP's rule: the end token has the largest id of its vocabulary).
* A text longer than `max_length` tokens in all (CLIP: 77, its position embeddings) is cut, with a warning,
  to its first `max_length - 2` tokens, and the end token is kept.

`tokenizers` is imported here only, when a CLIP tokenizer is made: MiniLM's path never loads it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.tokenizer import pad_batch, wrap_ids

MAX_TOKENIZER_BYTES = 64 << 20   # CLIP's tokenizer.json is ~3.5 MB; never parse a huge file


class ClipTokenizer:
    """A `tokenizer.json` with a start/end template. `encode(texts)` -> (input_ids, attention_mask)."""

    def __init__(self, path: str | Path, max_length: int = 77):
        self.path = Path(path)
        if not self.path.is_file():
            raise AgoInputError(path, "tokenizer file not found")
        if self.path.stat().st_size > MAX_TOKENIZER_BYTES:
            raise AgoInputError(path, f"larger than {MAX_TOKENIZER_BYTES >> 20} MiB; not a tokenizer.json")
        try:
            from tokenizers import Tokenizer
        except ImportError:
            raise AgoInputError(path, "reading a CLIP tokenizer needs the `tokenizers` package: "
                                "pip install 'tokenizers>=0.15,<0.24'") from None
        try:
            self.backend = Tokenizer.from_file(str(self.path))
        except Exception as e:   # tokenizers raises its own Exception subclasses for every bad file
            raise AgoInputError(path, f"not a tokenizer.json the tokenizers library reads ({str(e).splitlines()[0][:120]})") from None
        self.backend.no_padding()
        self.backend.no_truncation()
        wrap = self.backend.encode("").ids
        if len(wrap) != 2:
            raise AgoInputError(path, f"its post-processor wraps a text in {len(wrap)} special tokens, a CLIP "
                                "tokenizer adds two (<|startoftext|> and <|endoftext|>)")
        self.bos_id, self.eos_id = int(wrap[0]), int(wrap[1])
        self.pad_id = self.eos_id
        if max_length < 3:
            raise ValueError("max_length must leave room for the start token, a token and the end token")
        self.max_length = int(max_length)

    def tokenize_ids(self, text: str) -> list[int]:
        """The BPE ids of `text`, without the start and end tokens and without truncation."""
        return list(self.backend.encode(text, add_special_tokens=False).ids)

    def encode(self, texts: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """(input_ids, attention_mask), both int64 (B, L) with L = the longest item, right-padded with the end id."""
        if isinstance(texts, str):
            raise TypeError("encode takes a list of strings")
        # one text at a time: encode_batch runs a thread pool, and a process forked after it prints a warning
        rows = [wrap_ids(self.tokenize_ids(t), self.bos_id, self.eos_id, self.max_length, t, "BPE tokens")
                for t in texts]
        return pad_batch(rows, self.pad_id)
