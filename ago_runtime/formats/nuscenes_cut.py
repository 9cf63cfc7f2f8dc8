"""A train/val cut of a one-scene nuScenes dataroot, as a new dataroot, and the table rule every cut writes with
(`write_parts`: also ago_train/time_split.py's split by time) (issue 35: select a recipe on
held-out training frames, score the test frames once; `python -m benchmarks.dataroot_cut` runs it).

`cut_dataroot(SRC, DST, train, val)`: DST gets the first TRAIN + VAL keyframes (time order) of SRC's one
scene, split into two scenes, "<scene>-train" (the first TRAIN) and "<scene>-val" (the next VAL), and a
splits.json naming them, so every `ago` verb's `--split train` / `val` (and `ago train`'s train_split)
takes exactly those frames. Because they are two scenes, `ago pseudo-labels --keyframes K` superimposes
neighbours from inside the frame's own part only: no train pseudo-label ever uses a val keyframe's LiDAR or
boxes.

What is written: DST/<version>/ with every table of SRC (sample, sample_data and sample_annotation
kept for the chosen keyframes only, links to dropped records emptied; scene.json the two scenes; the
other tables copied), DST/splits.json, DST/cut.json (what was asked, to reuse the cut), and DST/samples
as a symbolic link to SRC/samples (no image or LiDAR file is copied). Built in a temporary folder and
renamed, so an interrupted run leaves no half-made DST. Bad input raises AgoInputError.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from ago_runtime.errors import AgoInputError

__all__ = ["cut_dataroot", "write_parts", "read_table", "write_table"]

# the tables whose records belong to one sample (kept only for the chosen keyframes)
PER_SAMPLE_TABLES = ("sample_data", "sample_annotation")


def read_table(path: Path):
    with open(path) as f:
        return json.load(f)


def write_table(path: Path, obj) -> None:
    with open(path, "w") as f:
        json.dump(obj, f)


def write_parts(src: Path, tmp: Path, version: str, parts_of_scene: dict[str, dict[str, list[dict]]],
                scenes: list[dict]) -> None:
    """Write the tables of SRC to TMP/<version> with each scene cut into its parts (`{scene token: {part:
    sample records in time order}}`), the sample links at each part's ends emptied, and the data folders linked."""
    new_scenes, scene_of = [], {}
    for scene in scenes:
        for part, recs in parts_of_scene[scene["token"]].items():
            token = f"{scene['token']}-{part}"
            new_scenes.append({**scene, "token": token, "name": f"{scene['name']}-{part}", "nbr_samples": len(recs),
                               "first_sample_token": recs[0]["token"], "last_sample_token": recs[-1]["token"]})
            scene_of.update({r["token"]: token for r in recs})
    kept = [dict(r, scene_token=scene_of[r["token"]]) for parts in parts_of_scene.values()
            for recs in parts.values() for r in recs]
    for r in kept:   # a link to a keyframe of another part (or dropped) is emptied
        for key in ("prev", "next"):
            if r.get(key) and scene_of.get(r[key]) != r["scene_token"]:
                r[key] = ""
    (tmp / version).mkdir(parents=True)
    poses: set[str] = set()   # the ego poses the kept sample_data use (official ego_pose.json is ~2.6M records)
    tables = sorted(src.joinpath(version).glob("*.json"), key=lambda t: (t.stem != "sample_data", t.name))
    for table in tables:
        name = table.stem
        if name == "ego_pose" and poses:
            records = [r for r in read_table(table) if r.get("token") in poses]
        elif name == "scene":
            records = new_scenes
        elif name == "sample":
            records = kept
        elif name in PER_SAMPLE_TABLES:
            records = [r for r in read_table(table) if r.get("sample_token") in scene_of]
            tokens = {r["token"] for r in records}
            poses.update(r["ego_pose_token"] for r in records if r.get("ego_pose_token"))
            for r in records:
                for key in ("prev", "next"):
                    if r.get(key) and r[key] not in tokens:
                        r[key] = ""
        else:
            shutil.copyfile(table, tmp / version / table.name)
            continue
        write_table(tmp / version / table.name, records)
    for folder in ("samples", "sweeps"):
        if (src / folder).is_dir():
            os.symlink(src / folder, tmp / folder)


def cut_dataroot(src: str | Path, dst: str | Path, train: int, val: int) -> dict:
    """Write the cut (see the module docstring) to `dst` and return its cut.json record; an existing
    `dst` made with the same source and counts is reused, any other `dst` is refused."""
    src, dst = Path(src).resolve(), Path(dst)
    asked = {"source": str(src), "train": train, "val": val}
    if dst.exists():
        marker = dst / "cut.json"
        if marker.is_file() and {k: read_table(marker).get(k) for k in asked} == asked:
            return read_table(marker)
        raise AgoInputError(dst, f"exists and is not a cut of {src} with train={train}, val={val}")
    if train < 1 or val < 1:
        raise AgoInputError("--train/--val", f"need at least 1 keyframe each, got {train}, {val}")
    versions = sorted(p.name for p in src.glob("v1.0-*") if p.is_dir())
    if len(versions) != 1:
        raise AgoInputError(src, f"needs exactly one v1.0-* table folder, found {versions}")
    version = versions[0]
    scenes = read_table(src / version / "scene.json")
    if len(scenes) != 1:
        raise AgoInputError(src / version / "scene.json", f"the cut takes a one-scene dataroot, "
                                                         f"this one has {len(scenes)} scenes")
    scene = scenes[0]
    samples = sorted(read_table(src / version / "sample.json"), key=lambda r: int(r["timestamp"]))
    if train + val > len(samples):
        raise AgoInputError("--train/--val", f"{train} + {val} keyframes asked, the scene has {len(samples)}")

    parts = {"train": samples[:train], "val": samples[train:train + val]}
    tmp = dst.with_name(dst.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    write_parts(src, tmp, version, {scene["token"]: parts}, [scene])
    write_table(tmp / "splits.json", {part: [f"{scene['name']}-{part}"] for part in parts})
    record = {**asked, "scene": scene["name"], "version": version,
              "train_tokens": [r["token"] for r in parts["train"]], "val_tokens": [r["token"] for r in parts["val"]]}
    write_table(tmp / "cut.json", record)
    os.replace(tmp, dst)
    return record
