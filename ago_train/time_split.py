"""A split of a nuScenes dataroot by time, written as a new dataroot: each chosen scene's keyframes become
three scenes, "<scene>-train" (the first ones), "<scene>-val" (the next block) and "<scene>-test" (the last),
listed in a splits.json, so every `ago` verb's `--split train|val|test` takes exactly those frames.

Because the parts are separate scenes, `ago pseudo-labels --keyframes K` superimposes neighbours from
inside a frame's own part only: no training pseudo-label uses a val or test keyframe's LiDAR or boxes.

`time_split(src, dst, val_share, test_share, max_scenes)`:
- scenes: those whose first keyframe's camera files are present (a trimmed extract lists scenes it lacks
  the files of), in name order; more than `max_scenes` -> `max_scenes` of them evenly spaced over the list
  (a big official dataroot is subsampled by whole scenes, which keeps every scene's time order);
- per scene of n keyframes (time order): test = the last round(test_share * n), val = the round(val_share
  * n) before them, train = the rest (each at least 1; a scene of fewer than 3 keyframes is refused).
What is written: DST/<version>/ with every table of SRC (sample, sample_data and sample_annotation kept for the
chosen keyframes only, links to dropped records emptied, ego_pose cut to the poses the kept sample_data use,
scene.json the new scenes, the other tables copied),
DST/splits.json, DST/split.json (what was asked and the tokens of each part: the record a results file cites),
and DST/samples (and DST/sweeps when SRC has them) as symbolic links (no image or LiDAR file is copied).
Built in a temporary folder and renamed; an existing DST made with the same source and settings is reused
(its split.json is checked), any other DST is refused with one line.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from ago_runtime.errors import AgoInputError
from ago_runtime.formats.nuscenes_cut import read_table, write_parts, write_table   # the one table rule

PARTS = ("train", "val", "test")


def part_sizes(n: int, val_share: float, test_share: float) -> tuple[int, int, int]:
    """(train, val, test) keyframe counts of a scene of n keyframes (module docstring)."""
    test = max(1, int(round(test_share * n)))
    val = max(1, int(round(val_share * n)))
    return n - val - test, val, test


def time_split(src: str | Path, dst: str | Path, val_share: float = 0.15, test_share: float = 0.2,
               max_scenes: int = 3) -> dict:
    """Write the split (module docstring) to `dst` and return its split.json record."""
    src, dst = Path(src).resolve(), Path(dst)
    asked = {"source": str(src), "val_share": val_share, "test_share": test_share, "max_scenes": max_scenes}
    if dst.exists():
        marker = dst / "split.json"
        if marker.is_file() and {k: read_table(marker).get(k) for k in asked} == asked:
            return read_table(marker)
        raise AgoInputError(dst, f"exists and is not the time split of {src} asked ({asked}); remove it or choose another OUT")
    if not 0 < val_share < 1 or not 0 < test_share < 1 or val_share + test_share >= 1:
        raise AgoInputError("--val-share/--test-share", f"need 0 < shares and a sum < 1, got {val_share}, {test_share}")
    versions = sorted(p.name for p in src.glob("v1.0-*") if p.is_dir()) if src.is_dir() else []
    if len(versions) != 1:
        raise AgoInputError(src, f"not a nuScenes dataroot: needs exactly one v1.0-* table folder, found {versions}")
    version = versions[0]
    tables = src / version
    samples = read_table(tables / "sample.json")
    by_scene: dict[str, list[dict]] = {}
    for r in samples:
        by_scene.setdefault(r["scene_token"], []).append(r)
    first_cam = {}
    for r in read_table(tables / "sample_data.json"):
        if r.get("is_key_frame") and "/CAM_FRONT/" in "/" + r.get("filename", ""):
            first_cam[r["sample_token"]] = r["filename"]
    scenes = []
    for s in sorted(read_table(tables / "scene.json"), key=lambda s: s["name"]):
        recs = sorted(by_scene.get(s["token"], []), key=lambda r: int(r["timestamp"]))
        if recs and recs[0]["token"] in first_cam and (src / first_cam[recs[0]["token"]]).is_file():
            scenes.append((s, recs))
    if not scenes:
        raise AgoInputError(src, "no scene whose keyframe camera files are present")
    if len(scenes) > max_scenes:
        scenes = [scenes[int(k * len(scenes) / max_scenes)] for k in range(max_scenes)]
    parts_of_scene = {}
    for s, recs in scenes:
        if len(recs) < 3:
            raise AgoInputError(tables / "scene.json", f"scene {s['name']} has {len(recs)} keyframes; a time split needs >= 3")
        n_train, n_val, n_test = part_sizes(len(recs), val_share, test_share)
        if n_train < 1:
            raise AgoInputError("--val-share/--test-share", f"leave no training keyframe of scene {s['name']} ({len(recs)})")
        parts_of_scene[s["token"]] = {"train": recs[:n_train], "val": recs[n_train:n_train + n_val],
                                      "test": recs[n_train + n_val:]}
    tmp = dst.with_name(dst.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    write_parts(src, tmp, version, parts_of_scene, [s for s, _ in scenes])
    write_table(tmp / "splits.json", {part: [f"{s['name']}-{part}" for s, _ in scenes] for part in PARTS})
    record = {**asked, "version": version, "scenes_in_source": len(by_scene),
              "scenes": {s["name"]: {part: [r["token"] for r in parts_of_scene[s["token"]][part]] for part in PARTS}
                         for s, _ in scenes}}
    write_table(tmp / "split.json", record)
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.replace(tmp, dst)
    return record
