"""Training from several (dataset, pseudo-label folder) pairs at once: `TrainConfig.sources`.

    "sources": [{"data": "work/real", "pseudo": "work/real-pseudo", "weight": 1},
                {"data": "work/town", "pseudo": "work/town-pseudo", "weight": 0.5, "split": "all"}]

Each source is a dataset root (any layout `open_dataset` reads), its pseudo-label folder, the split its
frames come from (default: the config's `train_split`) and a `weight`: how many times each of its frames
is seen per epoch (1 = once; 2 = twice; 0.5 = an evenly spaced half of its frames). Without `sources`
the config's `data` / `pseudo` / `train_split` are the one source (weight 1), as before.

What must agree, checked before any work, each a one-line error naming the source's folder:
- every pseudo-label folder is on the model's grid and in the prompt file's label space (`PseudoLabelSet.check`);
- every dataset's class table is the label space's (`check_label_table`);
- every source's cameras are the first source's (same names; their order may differ, each frame is put in the
  first source's order), so one model takes every frame;
- no sample (scene, token) is in two sources (a frame's pseudo-labels must be unambiguous).

`MixedFrames` is the frame sequence the trainer's dataset reads (a source's frames repeated per its
weight), and `PseudoSources` answers `labels` / `embeds` for a (scene, token) from that frame's own
pseudo-label folder, so every place that reads a training frame's labels (losses, the free prior, class
weights, calibration) reads the right folder. `open_split(data, gts, split)` opens one dataset and its split
(training and `ago eval` share it).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from ago_runtime.errors import AgoInputError

SOURCE_KEYS = ("data", "pseudo", "weight", "split", "gts")


@dataclass(frozen=True)
class Source:
    data: str
    pseudo: str
    weight: float = 1.0
    split: str | None = None   # None: the config's train_split
    gts: str | None = None


def check_sources(sources, where: str) -> None:
    """AgoInputError naming `where` unless `sources` is None or a non-empty list of source objects."""
    if sources is None:
        return
    if not isinstance(sources, (list, tuple)) or not sources:
        raise AgoInputError(where, f"sources must be a non-empty list of {{data, pseudo, weight}} objects or null, got {sources!r}")
    for n, s in enumerate(sources):
        if not isinstance(s, dict):
            raise AgoInputError(where, f"sources[{n}] must be an object with data, pseudo (and weight, split), got {s!r}")
        unknown = sorted(set(s) - set(SOURCE_KEYS))
        if unknown:
            raise AgoInputError(where, f"sources[{n}]: unknown keys {unknown} (known: {list(SOURCE_KEYS)})")
        for key in ("data", "pseudo"):
            if not isinstance(s.get(key), str) or not s.get(key):
                raise AgoInputError(where, f"sources[{n}].{key} must be a non-empty string, got {s.get(key)!r}")
        for key in ("split", "gts"):
            if s.get(key) is not None and (not isinstance(s[key], str) or not s[key]):
                raise AgoInputError(where, f"sources[{n}].{key} must be a non-empty string or null, got {s[key]!r}")
        w = s.get("weight", 1.0)
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) or w <= 0:
            raise AgoInputError(where, f"sources[{n}].weight must be a number > 0, got {w!r}")


def sources_of(cfg) -> list[Source]:
    """The config's sources (`sources`, else its data / pseudo / train_split as one source of weight 1)."""
    if cfg.sources is None:
        return [Source(cfg.data, cfg.pseudo, 1.0, cfg.train_split, cfg.gts)]
    return [Source(s["data"], s["pseudo"], float(s.get("weight", 1.0)), s.get("split") or cfg.train_split,
                   s.get("gts")) for s in cfg.sources]


def repeat_by_weight(indices: Sequence[int], weight: float) -> list[int]:
    """`indices` seen `weight` times: whole copies, then an evenly spaced part for the fraction (at least one)."""
    n = len(indices)
    total = max(1, int(round(weight * n)))
    out = list(indices) * (total // n)
    rest = total - len(out)
    if rest:
        out += [indices[int(k * n / rest)] for k in range(rest)]
    return out


class MixedFrames:
    """The frames of several datasets as one sequence: entry i is `datasets[part[i]][index[i]]`.
    `key(i)` names the underlying frame (repeats of a frame share it: the dataset's item memory keeps one copy)."""

    def __init__(self, datasets: Sequence, entries: Sequence[tuple[int, int]]):
        self.datasets = list(datasets)
        self.entries = [(int(p), int(i)) for p, i in entries]

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, i: int):
        p, j = self.entries[i]
        return self.datasets[p][j]

    def key(self, i: int):
        return self.entries[i]

    def unique(self) -> list[int]:
        """One position per distinct frame (the first), in order."""
        seen, out = set(), []
        for n, e in enumerate(self.entries):
            if e not in seen:
                seen.add(e)
                out.append(n)
        return out


class PseudoSources:
    """`labels` / `embeds` of a (scene, token) read from the pseudo-label folder of the source it came from."""

    def __init__(self, sets: Sequence, frames_of_set: Sequence[Sequence[tuple[str, str]]], names: Sequence[str]):
        self.sets = list(sets)
        self.root = self.sets[0].root
        self._where: dict[tuple[str, str], int] = {}
        for n, keys in enumerate(frames_of_set):
            for key in keys:
                other = self._where.setdefault(tuple(key), n)
                if other != n:
                    raise AgoInputError(names[n], f"sample {key[0]}/{key[1]} is also in source {names[other]}; "
                                        "a frame may come from one source only")

    def of(self, scene: str, token: str):
        return self.sets[self._where[(scene, token)]]

    def labels(self, scene: str, token: str, mark_unlabelled_hits: bool = False):
        return self.of(scene, token).labels(scene, token, mark_unlabelled_hits=mark_unlabelled_hits)

    def embeds(self, scene: str, token: str):
        return self.of(scene, token).embeds(scene, token)


def open_split(data: str | Path, gts: str | None, split: str, load_images: bool = True):
    """The dataset at `data` (`ago_runtime.formats.datasets.open_dataset`: the nuScenes or the Occ3D-Waymo
    layout; GT from `gts`, else where the layout keeps it) and its indices in `split`."""
    from ago_runtime.formats.datasets import open_dataset

    root = Path(data)
    if not root.exists():
        raise AgoInputError(root, "dataset root not found (make a synthetic one with `ago synth`)")
    ds = open_dataset(root, gts_root=gts, load_images=load_images, load_extras=False)
    indices = ds.split(split)
    note = ds.split_note(split)
    if note:   # no splits.json: say which default split is used
        print(f"note: using {note}", file=sys.stderr, flush=True)
    return ds, list(indices)


def open_sources(cfg, grid, label_space, load_images: bool):
    """(MixedFrames, PseudoSources, the first frame's rig) for the config's sources, everything checked
    (module docstring) before any file is written."""
    from ago_runtime.formats.datasets import check_label_table

    from .dataset import PseudoLabelSet

    srcs = sources_of(cfg)
    datasets, entries, sets, keys, names = [], [], [], [], []
    first_rig = None
    for n, src in enumerate(srcs):
        pseudo = PseudoLabelSet.open(src.pseudo)
        pseudo.check(grid, label_space.class_names)
        ds, indices = open_split(src.data, src.gts, src.split, load_images=load_images)
        check_label_table(ds, label_space)   # the pseudo-labels' classes index the data's class table
        if cfg.frame_tokens is not None:
            wanted = set(cfg.frame_tokens)
            indices = [i for i in indices if ds.sample_tokens[i] in wanted]
        if cfg.max_frames is not None:
            indices = indices[: cfg.max_frames]
        if not indices:
            raise AgoInputError(src.data, f"no frames in split {src.split!r}")
        frame_keys = [(ds.scene_of(i), ds.sample_tokens[i]) for i in indices]
        pseudo.check_files(frame_keys)
        rig = ds[indices[0]].rig
        if first_rig is None:
            first_rig = rig
        elif sorted(rig.names) != sorted(first_rig.names):
            raise AgoInputError(src.data, f"its frames have the cameras {list(rig.names)} but the first source's "
                                f"({srcs[0].data}) have {list(first_rig.names)}; every source must share one rig")
        datasets.append(ds)
        entries += [(n, i) for i in repeat_by_weight(indices, src.weight)]
        sets.append(pseudo)
        keys.append(frame_keys)
        names.append(str(Path(src.data)))
    return MixedFrames(datasets, entries), PseudoSources(sets, keys, names), first_rig
