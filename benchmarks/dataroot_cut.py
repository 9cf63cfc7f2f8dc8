"""A train/val cut of a one-scene nuScenes dataroot, as a new dataroot (issue 35: select a recipe on
held-out training frames, score the test frames once).

    python benchmarks/dataroot_cut.py SRC DST --train 22 --val 8

DST gets the first TRAIN + VAL keyframes (time order) of SRC's one scene, split into two scenes,
"<scene>-train" (the first TRAIN) and "<scene>-val" (the next VAL), and a splits.json naming them, so
every `ago` verb's `--split train` / `val` (and `ago train`'s train_split) takes exactly those frames.
Because they are two scenes, `ago pseudo-labels --keyframes K` superimposes neighbours from inside the
frame's own part only: no train pseudo-label ever uses a val keyframe's LiDAR or boxes.

What is written: DST/<version>/ with every table of SRC (sample, sample_data and sample_annotation
kept for the chosen keyframes only, links to dropped records emptied; scene.json the two scenes; the
other tables copied), DST/splits.json, DST/cut.json (what was asked, to reuse the cut), and DST/samples
as a symbolic link to SRC/samples (no image or LiDAR file is copied). Built in a temporary folder and
renamed, so an interrupted run leaves no half-made DST.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ago_train.time_split import read_table as _read, write_parts, write_table as _write  # noqa: E402


class CutError(Exception):
    """Bad input to the cut; main() prints it as one `error: ...` line and exits 2."""


def cut_dataroot(src: str | Path, dst: str | Path, train: int, val: int) -> dict:
    """Write the cut (see the module docstring) to `dst` and return its cut.json record; an existing
    `dst` made with the same source and counts is reused, any other `dst` is refused."""
    src, dst = Path(src).resolve(), Path(dst)
    asked = {"source": str(src), "train": train, "val": val}
    if dst.exists():
        marker = dst / "cut.json"
        if marker.is_file() and {k: _read(marker).get(k) for k in asked} == asked:
            return _read(marker)
        raise CutError(f"{dst}: exists and is not a cut of {src} with train={train}, val={val}")
    if train < 1 or val < 1:
        raise CutError(f"--train/--val: need at least 1 keyframe each, got {train}, {val}")
    versions = sorted(p.name for p in src.glob("v1.0-*") if p.is_dir())
    if len(versions) != 1:
        raise CutError(f"{src}: needs exactly one v1.0-* table folder, found {versions}")
    version = versions[0]
    scenes = _read(src / version / "scene.json")
    if len(scenes) != 1:
        raise CutError(f"{src / version / 'scene.json'}: the cut takes a one-scene dataroot, "
                         f"this one has {len(scenes)} scenes")
    scene = scenes[0]
    samples = sorted(_read(src / version / "sample.json"), key=lambda r: int(r["timestamp"]))
    if train + val > len(samples):
        raise CutError(f"--train/--val: {train} + {val} keyframes asked, the scene has {len(samples)}")

    parts = {"train": samples[:train], "val": samples[train:train + val]}
    tmp = dst.with_name(dst.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    write_parts(src, tmp, version, {scene["token"]: parts}, [scene])   # the tables, cut (ago_train/time_split.py)
    _write(tmp / "splits.json", {part: [f"{scene['name']}-{part}"] for part in parts})
    record = {**asked, "scene": scene["name"], "version": version,
              "train_tokens": [r["token"] for r in parts["train"]], "val_tokens": [r["token"] for r in parts["val"]]}
    _write(tmp / "cut.json", record)
    os.replace(tmp, dst)
    return record


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", help="a one-scene nuScenes dataroot")
    ap.add_argument("dst", help="the new dataroot (made; reused when it is the same cut)")
    ap.add_argument("--train", type=int, required=True, help="first TRAIN keyframes: split 'train'")
    ap.add_argument("--val", type=int, required=True, help="the next VAL keyframes: split 'val'")
    args = ap.parse_args(argv)
    try:
        rec = cut_dataroot(args.src, args.dst, args.train, args.val)
    except CutError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    print(f"{args.dst}: {rec['scene']} keyframes 0-{args.train - 1} = train, "
          f"{args.train}-{args.train + args.val - 1} = val")


if __name__ == "__main__":
    main()
