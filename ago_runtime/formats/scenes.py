"""Keyframes grouped by scene, the index rules both dataset readers share (`NuScenesDataset`,
`Occ3DWaymoDataset`): keyframes are sorted so that each scene's are contiguous and in time order.

- `scene_spans(scene_names)`: per keyframe index, the [start, end) of its scene;
- `neighbour_indices(span, i, count, interval)`: up to `count` keyframes of i's scene at offsets
  +interval*k, -interval*k (k = 1, 2, ...), nearest first (+ before -); a side that reaches its scene end
  stops and the other goes on (the keyframes pseudo-labels superimpose);
- `indices_of(names, index, scene_names, source)`: indices of sample tokens and/or scene names, in the
  order given; every unknown name listed in one AgoInputError naming `source`.
"""

from __future__ import annotations

from ago_runtime.errors import AgoInputError


def scene_spans(scene_names: list[str]) -> list[tuple[int, int]]:
    """[start, end) of each index's scene (the indices of one scene are contiguous)."""
    spans: list[tuple[int, int]] = []
    start = 0
    for i in range(1, len(scene_names) + 1):
        if i == len(scene_names) or scene_names[i] != scene_names[start]:
            spans.extend([(start, i)] * (i - start))
            start = i
    return spans


def neighbour_indices(span: tuple[int, int], i: int, count: int, interval: int) -> list[int]:
    """Up to `count` indices of the scene `span` = [start, end) around i (see the module docstring)."""
    if count < 0 or interval < 1:
        raise AgoInputError(None, f"neighbours needs count >= 0 and interval >= 1, got {count}, {interval}")
    start, end = span
    out: list[int] = []
    k = 1
    while len(out) < count and (i + k * interval < end or i - k * interval >= start):
        for j in (i + k * interval, i - k * interval):
            if start <= j < end and len(out) < count:
                out.append(j)
        k += 1
    return out


def indices_of(names: list[str], index: dict[str, int], scene_names: list[str], source, what: str) -> list[int]:
    """Indices of sample tokens (`index`: token -> index) and/or scene names, in the order given (a scene: its
    keyframes in time order); the unknown ones in one AgoInputError naming `source` ("no <what> ...")."""
    out, unknown = [], []
    scenes = set(scene_names)
    for name in names:
        if name in index:
            out.append(index[name])
        elif name in scenes:
            out += [i for i, s in enumerate(scene_names) if s == name]
        else:
            unknown.append(name)
    if unknown:
        raise AgoInputError(source, f"no {what} {', '.join(map(repr, unknown))}")
    return out
