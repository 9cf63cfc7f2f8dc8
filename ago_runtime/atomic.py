"""Atomic file writes: write to a temporary file beside the target, then rename.

A crash or a bad input never leaves a half-written file at the target path.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto `path` on success.

    The temporary name keeps the target's suffix (np.savez, cv2.imwrite and onnx look at it).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = suffix if suffix is not None else "".join(path.suffixes)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        if tmp.exists():  # mkstemp makes 0600 files; give the result the usual umask-based mode
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def save_npz(path: str | os.PathLike, compressed: bool = True, compresslevel: int | None = None,
             **arrays: np.ndarray) -> None:
    """np.savez(_compressed) written atomically. Never uses pickle (object arrays are refused).
    compresslevel (1-9, with compressed): the deflate level instead of numpy's 6; `ago infer` writes with 1
    (faster to write, a little larger); np.load reads either."""
    for k, v in arrays.items():
        if np.asarray(v).dtype == object:
            raise TypeError(f"array {k!r} has dtype object; npz files here never hold pickles")
    with atomic_path(path, suffix=".npz") as tmp:
        if compressed and compresslevel is not None:
            import zipfile

            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=int(compresslevel)) as zf:
                for k, v in arrays.items():
                    with zf.open(f"{k}.npy", "w", force_zip64=True) as f:
                        np.lib.format.write_array(f, np.asanyarray(v), allow_pickle=False)
            return
        with open(tmp, "wb") as f:
            (np.savez_compressed if compressed else np.savez)(f, **arrays)


# ---- folders -------------------------------------------------------------------------------------
# A folder (e.g. an exported bundle) is built in a hidden temporary folder beside its target, named
# `.<name>.tmp-<pid>-<random>`, and swapped into place at the end. A run that was killed leaves its
# temporary folder behind; the next `temp_dir_beside` for the same target removes every such folder
# whose process is gone (and restores a target a killed fallback swap had moved aside).

def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _leftovers(out: Path, kind: str) -> list[tuple[Path, int]]:
    """(path, pid) of `.<name>.<kind>-<pid>-...` folders beside `out`."""
    found = []
    for p in out.parent.glob(f".{out.name}.{kind}-*"):
        pid = p.name[len(f".{out.name}.{kind}-"):].split("-", 1)[0]
        if pid.isdigit():
            found.append((p, int(pid)))
    return found


def clean_stale_dirs(out: str | os.PathLike) -> list[Path]:
    """Remove temporary folders of dead runs beside `out`; put back a target left moved aside. Gives what was removed."""
    import shutil

    out = Path(out)
    removed = []
    if not out.parent.is_dir():
        return removed
    for old, pid in _leftovers(out, "old"):
        if _pid_alive(pid):
            continue
        if not out.exists():          # a fallback swap was killed between its two renames
            old.rename(out)
        else:
            shutil.rmtree(old, ignore_errors=True)
            removed.append(old)
    for tmp, pid in _leftovers(out, "tmp"):
        if not _pid_alive(pid):
            shutil.rmtree(tmp, ignore_errors=True)
            removed.append(tmp)
    return removed


def temp_dir_beside(out: str | os.PathLike) -> Path:
    """A new empty hidden folder next to `out` to build it in (stale ones of dead runs removed first)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_dirs(out)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-{os.getpid()}-", dir=out.parent))


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux renameat2 RENAME_EXCHANGE); False where the system cannot."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    AT_FDCWD, RENAME_EXCHANGE = -100, 2
    rc = renameat2(AT_FDCWD, os.fsencode(str(a)), AT_FDCWD, os.fsencode(str(b)), RENAME_EXCHANGE)
    return rc == 0


def replace_dir(tmp: str | os.PathLike, out: str | os.PathLike) -> None:
    """Put the finished folder `tmp` at `out`, replacing what is there, so that `out` is never missing:
    an atomic exchange where the system has one (then the old folder, now at `tmp`, is deleted); else
    out -> `.<name>.old-<pid>`, tmp -> out, and a kill between the two is undone by the next
    clean_stale_dirs(out)."""
    import shutil

    tmp, out = Path(tmp), Path(out)
    if not out.exists():
        tmp.rename(out)
        return
    if _exchange(tmp, out):
        shutil.rmtree(tmp, ignore_errors=True)
        return
    old = out.with_name(f".{out.name}.old-{os.getpid()}")
    if old.exists():
        shutil.rmtree(old)
    out.rename(old)
    tmp.rename(out)
    shutil.rmtree(old, ignore_errors=True)
