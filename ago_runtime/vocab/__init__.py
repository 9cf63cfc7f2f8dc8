"""ago_runtime.vocab: the vocabulary - prompt files, label spaces, text encoders and prompt banks.

Holds `prompts` (prompt files -> LabelSpace), `tokenizer` (MiniLM's WordPiece in pure python),
`clip_tokenizer` (CLIP's BPE from a tokenizer.json, with the `tokenizers` library, loaded on that path only),
`text_encoder` (the ONNX sentence encoder and where to find it), `model_folder` (the user's save_pretrained
folders: checks, `clip:<hash>` ids, a CLIP folder's torch text tower by name), `bank` (PromptBank files, and
`load_prompt_bank`, the one way a prompt file becomes a bank) and `cli` (`ago prompts build|show`).

The one vocabulary path (used by infer, retrieve, demo, training, pseudo-labels and export):
    prompt file --parse_prompt_file--> LabelSpace --load_prompt_bank--> cached bank (by content
    hash) --> PromptBank

May import: numpy, onnxruntime, ago_runtime's basics. Nothing else in ago_runtime (a bundle is
taken as an argument, never imported); `cli` may also import typer.
"""

from ago_runtime.vocab.bank import PromptBank, load_prompt_bank
from ago_runtime.vocab.prompts import LabelSpace, parse_prompt_file

__all__ = ["LabelSpace", "PromptBank", "load_prompt_bank", "parse_prompt_file"]
