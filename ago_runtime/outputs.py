"""Check, before any work, that a verb can write where it was told to (one clear error otherwise).

`check_output_dir(path, option)` and `check_output_file(path, option)` raise AgoInputError naming
the path when:
- a component of the path that exists is a file where a folder is needed (`--out results.txt/x`);
- the path itself exists with the wrong kind (a file where a folder is wanted, a folder where a
  file is wanted, a device such as /dev/null where a file is wanted: it would be renamed over);
- nothing can be created there: read-only folder or file system, no permission, a kernel file
  system such as /sys or /proc. This is tested by really creating (and at once deleting) an empty
  probe file in the nearest existing folder, since permission bits alone do not tell (root ignores
  them, a read-only mount does not show in them).
Nothing is left behind: no folder is created, the probe file is removed.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ago_runtime.errors import AgoInputError


def _nearest_existing(path: Path) -> Path:
    """The deepest existing ancestor of `path` (or `path` itself); refuses a file on the way."""
    p = path
    while not p.exists():
        if p.is_symlink():   # a dangling link: its target cannot be made safely
            raise AgoInputError(p, "is a broken symbolic link")
        p = p.parent
    if not p.is_dir() and p != path:
        raise AgoInputError(path, f"{p} is a file, not a folder")
    return p


def _probe(folder: Path, target: Path) -> None:
    try:
        fd, name = tempfile.mkstemp(prefix=".ago-write-test-", dir=folder)
    except OSError as e:
        raise AgoInputError(target, f"cannot write here ({e.strerror or e.__class__.__name__} in {folder})") from None
    os.close(fd)
    try:
        os.unlink(name)
    except OSError:
        pass


def check_output_dir(path: str | os.PathLike, option: str | None = None) -> Path:
    """`path` is, or can become, a folder we can write files into. Gives it as a Path."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise AgoInputError(path, f"exists and is not a folder{f' ({option} needs a folder)' if option else ''}")
    _probe(_nearest_existing(path), path)
    return path


def check_output_file(path: str | os.PathLike, option: str | None = None) -> Path:
    """`path` is, or can become, a file we can (re)write atomically (temp file beside it + rename)."""
    path = Path(path)
    if path.is_dir():
        raise AgoInputError(path, f"is a folder{f'; {option} needs a file name' if option else '; give a file name'}")
    if str(path).endswith(os.sep) or path.name in ("", ".", ".."):
        raise AgoInputError(path, "is not a file name")
    if path.is_symlink() and not path.exists():
        raise AgoInputError(path, "is a broken symbolic link")
    if path.exists() and not path.is_file():   # a device, a pipe, a socket: never renamed over
        raise AgoInputError(path, "exists and is not a regular file")
    _probe(_nearest_existing(path.parent), path)
    return path


def check_distinct_outputs(*named) -> None:
    """(option, path or None) pairs: refuse two options naming one file (`--json x.json --md x.json`)."""
    seen: dict[str, str] = {}
    for option, path in named:
        if path is None:
            continue
        key = os.path.realpath(path)
        if key in seen:
            raise AgoInputError(path, f"{seen[key]} and {option} name the same file; give each its own")
        seen[key] = option


def check_suffix(path: str | os.PathLike, suffixes: tuple[str, ...], option: str) -> Path:
    """`path` when it ends in one of `suffixes` (what the verb writes: a PNG under a .jpg name is refused)."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise AgoInputError(option, f"{path}: writes {' or '.join(suffixes)} files; give a name ending in "
                                    f"{suffixes[0]}")
    return path
