#!/usr/bin/env bash
# Build the default bundle and demo frame that `ago demo` uses (the shipped ones were made by this
# script with its defaults):
#
#   synthetic city -> pseudo-labels (simulated segmenter + embedder) -> train (cpu preset)
#   -> ago export (parity-checked) -> ago_runtime/assets/default_bundle/ + assets/demo_frame/
#
# Needs the training extra (scripts/setup.sh). About 10 min of data + 30-40 min of training on a
# 2-core CPU. Usage: bash scripts/make_default_bundle.sh [WORK_DIR]
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WORK="${1:-$REPO/work/default_bundle}"
SCENES="${SCENES:-10}"
FRAMES="${FRAMES:-16}"
EPOCHS="${EPOCHS:-3}"
IMAGE_SIZE="${IMAGE_SIZE:-704x396}"
PROMPTS="${PROMPTS:-cw}"
PRESET="${PRESET:-cpu}"
GRID="${GRID:-100x100x8}"
ASSETS="$REPO/ago_runtime/assets"
AGO="python -m ago_runtime"
export AGO_NO_PROGRESS="${AGO_NO_PROGRESS:-0}"

mkdir -p "$WORK"
echo "== 1/5 synthetic data ($SCENES scenes x $FRAMES frames) -> $WORK/synth"
[ -d "$WORK/synth" ] || $AGO synth --out "$WORK/synth" --scenes "$SCENES" --frames "$FRAMES" --seed 0 \
    --image-size "$IMAGE_SIZE" --grid 200x200x16

echo "== 2/5 pseudo-labels ($PROMPTS, grid $GRID) -> $WORK/pseudo"
$AGO pseudo-labels --data "$WORK/synth" --out "$WORK/pseudo" --prompts "$PROMPTS" --grid "$GRID" --split train \
    --segmenter sim --embedder sim --keyframes 10 --interval 1

echo "== 3/5 train ($PRESET preset) -> $WORK/train"
$AGO train --config "$PRESET" --data "$WORK/synth" --pseudo "$WORK/pseudo" --prompts "$PROMPTS" --out "$WORK/train" \
    --set epochs="$EPOCHS" --set ckpt_every=50

echo "== 4/5 export (parity-checked on the real nuScenes keyframe when ../shared is present)"
$AGO export "$WORK/train/last.pt" -o "$WORK/bundle"

echo "== 5/5 copy into $ASSETS"
mkdir -p "$ASSETS"
rm -rf "$ASSETS/default_bundle.new" && cp -r "$WORK/bundle" "$ASSETS/default_bundle.new"
rm -rf "$ASSETS/default_bundle" && mv "$ASSETS/default_bundle.new" "$ASSETS/default_bundle"

# Demo frame: six JPEGs named by camera + calib.json, from the first val frame of the synthetic city
# (never real nuScenes images: their licence forbids bundling them).
python - "$WORK/synth" "$ASSETS/demo_frame" <<'PY'
import sys, shutil
from pathlib import Path
import cv2
from ago_runtime.calibration import save_calibration
from ago_runtime.nuscenes import NuScenesDataset

ds = NuScenesDataset(sys.argv[1], load_extras=False)
idx = ds.split("val") or list(range(len(ds)))
frame = ds[idx[0]]
out = Path(sys.argv[2])
tmp = out.with_name(out.name + ".new")
shutil.rmtree(tmp, ignore_errors=True)
tmp.mkdir(parents=True)
for cam in frame.rig:
    cv2.imwrite(str(tmp / f"{cam.name}.jpg"), cv2.cvtColor(frame.images[cam.name], cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_JPEG_QUALITY, 90])
save_calibration(tmp / "calib.json", frame.rig)
shutil.rmtree(out, ignore_errors=True)
tmp.rename(out)
print(f"demo frame {frame.token} -> {out}")
PY

echo "done: try  python -m ago_runtime demo"
