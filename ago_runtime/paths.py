"""The one path rule for names read from data files: they resolve under their root.

A data file names other files: an mmdetection3d info file its images and LiDAR sweeps, a nuScenes
`sample_data.json` its `filename`s, a bundle's `bundle.json` its ONNX graphs, heads and banks, an ONNX
graph its external data. `inside_root(root, name, source, what)` is the only place that turns such a
name into a path. It refuses (AgoInputError naming `source`, the data file that holds the name):
- a name that is not a non-empty string, or holds a NUL or another control character, or is longer
  than MAX_NAME_CHARS;
- an absolute name (`/etc/hostname`) or one with a `..` component (`../../../../etc/passwd`), i.e. any
  name that could leave `root` by its spelling, whether or not the file it names exists or is valid;
unless `allow_outside` is True (the user asked for it: `ago infer --allow-outside-root`), when the name
is joined as it is. The check is on the name, not on the resolved file: a folder of the data root that
is itself a symbolic link (a `samples/` kept on another disk) is the user's own choice and is followed.
"""

from __future__ import annotations

from pathlib import Path

from ago_runtime.errors import AgoInputError

MAX_NAME_CHARS = 4096


def name_problem(name) -> str | None:
    """None when `name` (read from a data file) stays under its root by its spelling, else what is wrong."""
    if not isinstance(name, str) or not name.strip():
        return f"name must be a non-empty string, got {str(name)[:80]!r}"
    if len(name) > MAX_NAME_CHARS:
        return f"name is {len(name)} characters long (at most {MAX_NAME_CHARS})"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return f"name {name[:80]!r} holds a control character"
    if name.startswith(("/", "\\", "~")) or (len(name) > 1 and name[1] == ":"):
        return f"{name[:200]!r} is an absolute path (names in data files must be relative to their root)"
    if ".." in name.replace("\\", "/").split("/"):
        return f"{name[:200]!r} leads outside its root ('..')"
    return None


def inside_root(root: str | Path, name, source, what: str = "file", allow_outside: bool = False) -> Path:
    """`root / name` for a `name` read from the data file `source`; AgoInputError naming `source` when the
    name would leave `root` (name_problem), unless `allow_outside` (the user's explicit option)."""
    if allow_outside and isinstance(name, str) and name.strip() and "\0" not in name:
        return Path(root) / name
    problem = name_problem(name)
    if problem:
        raise AgoInputError(source, f"{what} {problem}; refused: outside the data root {root}")
    return Path(root) / name
