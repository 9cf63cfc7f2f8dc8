"""Reading .npz files safely: never unpickles, checks the keys, one clear error naming the file.

(Writing goes through `ago_runtime.atomic.save_npz`.)
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from .errors import AgoInputError


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
