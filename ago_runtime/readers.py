"""Reading user files safely, with one clear AgoInputError naming the file.

- `read_npz`: never unpickles, checks the keys;
- `read_json`: UTF-8 JSON, optionally of a given top-level type; files over `max_json_bytes()` (4 GiB,
  $AGO_MAX_JSON_BYTES) are refused unread, nesting deeper than Python's parser takes is one error.
(Writing goes through `ago_runtime.atomic`.)
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError


MAX_ARRAY_BYTES = 1 << 30     # one array of an .npz may hold at most 1 GiB ($AGO_MAX_ARRAY_BYTES)


def max_array_bytes() -> int:
    env = os.environ.get("AGO_MAX_ARRAY_BYTES")
    return int(float(env)) if env else MAX_ARRAY_BYTES


def check_npz(path: str | Path, z) -> None:
    """Before any array of the open npz `z` (np.load's NpzFile) is read: every member's .npy header is read
    and the array it declares must be a plain dtype (no objects), at most max_array_bytes(), and no larger
    than the member's stored size (a header claiming 4 TB over 16 bytes of data is refused, not allocated)."""
    limit = max_array_bytes()
    for info in z.zip.infolist():
        if not info.filename.endswith(".npy"):
            continue
        with z.zip.open(info) as f:
            try:
                version = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(f)
            except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
                raise AgoInputError(path, f"{info.filename}: not a .npy array ({e})") from None
        if dtype.hasobject:
            raise AgoInputError(path, f"{info.filename}: an array of Python objects (ago never unpickles)")
        nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
        if nbytes > limit:
            raise AgoInputError(path, f"{info.filename}: declares {nbytes} bytes {tuple(shape)}, more than ago reads "
                                      f"({limit}; $AGO_MAX_ARRAY_BYTES sets the limit)")
        if nbytes > info.file_size:
            raise AgoInputError(path, f"{info.filename}: declares {nbytes} bytes but holds {info.file_size} "
                                      "(truncated or forged)")


def read_npz(path: str | Path, keys: tuple[str, ...] | list[str], what: str = "npz file") -> dict[str, np.ndarray]:
    """The arrays `keys` of an .npz file (allow_pickle=False, sizes checked first: check_npz); AgoInputError
    when missing, unreadable or incomplete."""
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, f"{what} not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            check_npz(path, z)
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise AgoInputError(path, f"missing keys {missing} (needs {list(keys)})")
            return {k: np.asarray(z[k]) for k in keys}
    except AgoInputError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise AgoInputError(path, f"not a readable npz file ({e.__class__.__name__}: {e})") from None


MAX_JSON_BYTES = 4 << 30    # a JSON file (a nuScenes table, a bundle.json, a calib.json) larger than this is refused


def max_json_bytes() -> int:
    env = os.environ.get("AGO_MAX_JSON_BYTES")
    return int(float(env)) if env else MAX_JSON_BYTES


def read_json(path: str | Path, missing: str = "file not found", expect: type | None = None):
    """The parsed JSON of `path`; AgoInputError `missing` when absent, or when unreadable / too big / too deeply
    nested / not of type `expect`."""
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, missing)
    size = path.stat().st_size
    if size > max_json_bytes():
        raise AgoInputError(path, f"JSON file of {size} bytes, more than ago reads ({max_json_bytes()}; "
                                  "$AGO_MAX_JSON_BYTES sets the limit)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except RecursionError:
        raise AgoInputError(path, "JSON nested too deeply") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise AgoInputError(path, f"not valid JSON ({e})") from None
    if expect is not None and not isinstance(data, expect):
        raise AgoInputError(path, f"expected a JSON {expect.__name__}, got {type(data).__name__}")
    return data
