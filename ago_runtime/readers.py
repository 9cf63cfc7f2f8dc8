"""Reading user files safely, with one clear AgoInputError naming the file.

- `open_npz` / `read_npz` / `read_npy`: never unpickle; every .npy header is read and checked against the
  array bound ($AGO_MAX_ARRAY_BYTES, 1 GiB) and the stored size before any data (`check_npy_header`);
- `read_json`: UTF-8 JSON, optionally of a given top-level type; files over `max_json_bytes()` (4 GiB,
  $AGO_MAX_JSON_BYTES) are refused unread, nesting deeper than Python's parser takes is one error.
(Writing goes through `ago_runtime.atomic`.)
"""

from __future__ import annotations

import contextlib
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


def check_npy_header(f, path, member: str = "", stored: int | None = None) -> tuple:
    """Read the .npy header at f's position (magic, then the header; no data) -> (shape, dtype), refusing an
    array of Python objects, one whose shape bounds more than max_array_bytes() (each axis counted at least
    once, so that an empty array declaring 10^12 rows is refused too: code sizes its work from the shape), and
    one declaring more bytes than the `stored` bytes it holds. AgoInputError(path, "<member>: ...")."""
    where = f"{member}: " if member else ""
    try:
        version = np.lib.format.read_magic(f)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(f)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise AgoInputError(path, f"{where}not a .npy array ({e})") from None
    if dtype.hasobject:
        raise AgoInputError(path, f"{where}an array of Python objects (ago never unpickles)")
    limit = max_array_bytes()
    bound = int(np.prod([max(int(d), 1) for d in shape], dtype=object)) * max(dtype.itemsize, 1)
    if bound > limit:
        raise AgoInputError(path, f"{where}declares shape {tuple(shape)} {dtype}, more than ago reads ({limit} bytes; "
                                  "$AGO_MAX_ARRAY_BYTES sets the limit)")
    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if stored is not None and nbytes > stored:
        raise AgoInputError(path, f"{where}declares {nbytes} bytes but holds {stored} (truncated or forged)")
    return tuple(shape), dtype


def check_npz(path: str | Path, z) -> None:
    """Before any array of the open npz `z` (np.load's NpzFile) is read: every member's .npy header is checked
    (check_npy_header against the member's stored size)."""
    for info in z.zip.infolist():
        if not info.filename.endswith(".npy"):
            continue
        with z.zip.open(info) as f:
            check_npy_header(f, path, info.filename, info.file_size)


@contextlib.contextmanager
def open_npz(path: str | Path, what: str = "npz file"):
    """`with open_npz(path) as z:` np.load(path, allow_pickle=False) with every member's header checked first
    (check_npz); the one way ago opens an .npz it did not just write. A missing file, an unreadable one, or a
    read inside the block that fails (a truncated member, a missing key) is one AgoInputError naming `path`."""
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, f"{what} not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            check_npz(path, z)
            yield z
    except AgoInputError:
        raise
    except KeyError as e:
        raise AgoInputError(path, f"{what} lacks array {e}") from None
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise AgoInputError(path, f"not a readable npz file ({what}; {e.__class__.__name__}: {e})") from None


def read_npy(path: str | Path, what: str = ".npy file") -> np.ndarray:
    """One .npy file, its header checked first (check_npy_header against the file's size), never unpickled."""
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, f"{what} not found")
    try:
        with open(path, "rb") as f:
            check_npy_header(f, path, stored=path.stat().st_size)
        return np.load(path, allow_pickle=False)
    except AgoInputError:
        raise
    except (OSError, ValueError, EOFError) as e:
        raise AgoInputError(path, f"not a readable .npy file ({what}; {e.__class__.__name__}: {e})") from None


def read_npz(path: str | Path, keys: tuple[str, ...] | list[str], what: str = "npz file") -> dict[str, np.ndarray]:
    """The arrays `keys` of an .npz file (open_npz: headers checked first); AgoInputError when missing,
    unreadable or incomplete."""
    with open_npz(path, what) as z:
        missing = [k for k in keys if k not in z.files]
        if missing:
            raise AgoInputError(path, f"missing keys {missing} (needs {list(keys)})")
        return {k: np.asarray(z[k]) for k in keys}


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
