"""Reading user files safely, with one clear AgoInputError naming the file.

- `read_npz`: never unpickles, checks the keys;
- `read_json`: UTF-8 JSON, optionally of a given top-level type.
(Writing goes through `ago_runtime.atomic`.)
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError


def read_npz(path: str | Path, keys: tuple[str, ...] | list[str], what: str = "npz file") -> dict[str, np.ndarray]:
    """The arrays `keys` of an .npz file (allow_pickle=False); AgoInputError when missing, unreadable or incomplete."""
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, f"{what} not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise AgoInputError(path, f"missing keys {missing} (needs {list(keys)})")
            return {k: np.asarray(z[k]) for k in keys}
    except AgoInputError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise AgoInputError(path, f"not a readable npz file ({e.__class__.__name__}: {e})") from None


def read_json(path: str | Path, missing: str = "file not found", expect: type | None = None):
    """The parsed JSON of `path`; AgoInputError `missing` when absent, or when unreadable / not of type `expect`."""
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, missing)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise AgoInputError(path, f"not valid JSON ({e})") from None
    if expect is not None and not isinstance(data, expect):
        raise AgoInputError(path, f"expected a JSON {expect.__name__}, got {type(data).__name__}")
    return data
