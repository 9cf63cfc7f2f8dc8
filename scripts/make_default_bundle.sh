#!/usr/bin/env bash
# Build the default bundle and demo frame that `ago demo` uses (the shipped ones were made by this
# script with its defaults):
#
#   synthetic city -> pseudo-labels (simulated segmenter + embedder, --carve grazing, --moving track) -> train (cpu
#   preset, 100x100x16, decoder width 64)
#   -> the model kept (last.pt without optimiser state; models/default/) -> ago eval (val split, read out on
#   the GT's 200x200x16) -> ago export (read out on 200x200x16, parity-checked, with its bundle card)
#   -> ago_runtime/assets/default_bundle/ + assets/demo_frame/
#
# After a bundle format change, scripts/export_default_bundle.sh exports the shipped bundle again from the kept
# models/default/checkpoint.pt (no training).
#
# Another rig (issue 38): RIG=front|waymo LAYOUT=nuscenes (ago synth --rig/--layout) trains the same recipe on that
# rig's cameras; set the model's canvas to the rig's aspect with MODEL_SIZE=WxH (e.g. 384x256 for Waymo's 3:2
# front camera). Only the default rig's bundle is copied into the package (INSTALL=1 forces, INSTALL=0 skips).
# Needs the training extra (scripts/setup.sh). Each step's time is printed (measured runs, by stage:
# benchmarks/results/training_cpu.md); every step resumes or reuses what an interrupted run left. Usage:
#   bash scripts/make_default_bundle.sh [WORK_DIR]
# The training run keeps snapshots for the learning curve:
#   python -m benchmarks.learning_curve --run WORK_DIR/train --data WORK_DIR/synth --fresh FRESH_TOWN
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WORK="${1:-$REPO/work/default_bundle}"
SCENES="${SCENES:-24}"
FRAMES="${FRAMES:-16}"
# 4000 steps, the cpu preset's: the length that keeps the chain within an hour on a 2-core CPU
# (what longer runs scored: benchmarks/results/training_cpu.md)
STEPS="${STEPS:-4000}"
SNAPSHOTS="${SNAPSHOTS:-[250,500,1000,2000,3000,4000]}"
# the training town is rendered at half of 704x396: the model reads 352x192 anyway, and synth and the
# per-pixel pseudo-labels cost less (the towns it is scored on are rendered at 704x396)
IMAGE_SIZE="${IMAGE_SIZE:-352x198}"
PROMPTS="${PROMPTS:-cw}"
PRESET="${PRESET:-cpu}"
GRID="${GRID:-100x100x16}"   # the cpu preset's grid (0.8 x 0.8 x 0.4 m)
# the pseudo-labels' free-space rule (`ago pseudo-labels --carve`): grazing keeps far ground from being carved free
CARVE="${CARVE:-grazing}"
# the moving objects' rule (`ago pseudo-labels --moving`): track carries their points along their annotated box
# tracks; aggregate (the verb's default; the default model until 2026-12-07) superimposes them where they were in
# every keyframe (benchmarks/results/pseudo_moving_track.md)
MOVING="${MOVING:-track}"
# the grid the bundle predicts on: the model's TPV planes read at Occ3D's 0.4 m voxel centres (the
# synthetic GT's grid; `ago eval --readout gt`, docs/training.md). READOUT_GRID= (empty) keeps the model grid.
READOUT_GRID="${READOUT_GRID-200x200x16}"
JOBS="${JOBS:-2}"
RIG="${RIG:-nuscenes}"
LAYOUT="${LAYOUT:-nuscenes}"
MODEL_SIZE="${MODEL_SIZE:-}"
# the decoder's hidden width Dh: 64 about halves the per-voxel work of the cpu preset's 128 at the same scores
# (benchmarks/results/hidden_width.md); HIDDEN= (empty) keeps the preset's
HIDDEN="${HIDDEN-64}"
INSTALL="${INSTALL:-$([ "$RIG" = nuscenes ] && echo 1 || echo 0)}"
MODEL_SET=()
[ -n "$MODEL_SIZE" ] && MODEL_SET=(--set "model.image_width=${MODEL_SIZE%x*}" --set "model.image_height=${MODEL_SIZE#*x}")
[ -n "$HIDDEN" ] && MODEL_SET+=(--set "model.hidden_dim=$HIDDEN")
ASSETS="$REPO/ago_runtime/assets"
AGO="python -m ago_runtime"
export AGO_NO_PROGRESS="${AGO_NO_PROGRESS:-0}"
START=$SECONDS
stamp() { echo "   ($(( (SECONDS - START) / 60 )) min $(( (SECONDS - START) % 60 )) s so far)"; }

mkdir -p "$WORK"
echo "== 1/6 synthetic data ($SCENES scenes x $FRAMES frames, seed 0) -> $WORK/synth"
[ -f "$WORK/synth/splits.json" ] || { rm -rf "$WORK/synth"; $AGO synth --out "$WORK/synth" --scenes "$SCENES" \
    --frames "$FRAMES" --seed 0 --image-size "$IMAGE_SIZE" --grid 200x200x16 --jobs "$JOBS" --rig "$RIG" --layout "$LAYOUT"; }
stamp

echo "== 2/6 pseudo-labels ($PROMPTS, grid $GRID, --carve $CARVE, --moving $MOVING, train split) -> $WORK/pseudo"
$AGO pseudo-labels --data "$WORK/synth" --out "$WORK/pseudo" --prompts "$PROMPTS" --grid "$GRID" --carve "$CARVE" \
    --moving "$MOVING" --split train \
    --segmenter sim --embedder sim --keyframes 10 --interval 1 --jobs "$JOBS"
stamp

echo "== 3/6 train ($PRESET preset, $STEPS steps) -> $WORK/train"
RESUME=""
[ -f "$WORK/train/last.pt" ] && RESUME="--resume"
$AGO train --config "$PRESET" --data "$WORK/synth" --pseudo "$WORK/pseudo" --prompts "$PROMPTS" --out "$WORK/train" \
    --set max_steps="$STEPS" --set ckpt_every=250 --set "snapshot_steps=$SNAPSHOTS" "${MODEL_SET[@]}" $RESUME
stamp

echo "== 4/6 the model kept: last.pt without its optimiser state -> $WORK/model (evaluated on the val split there)"
# $WORK/model is what the repository keeps (models/default/): the checkpoint the shipped bundle is exported
# from, the run's log and config, and the val scores the bundle card reports; scripts/export_default_bundle.sh
# exports the shipped bundle again from it after a bundle format change, with no training.
READOUT_EVAL="model"
[ -n "$READOUT_GRID" ] && READOUT_EVAL="gt"
mkdir -p "$WORK/model"
python -c 'import sys; from ago_train.checkpoint import CheckpointContract as C; C.load(sys.argv[1]).model_only().save(sys.argv[2])' \
    "$WORK/train/last.pt" "$WORK/model/checkpoint.pt"
cp "$WORK/train/log.jsonl" "$WORK/train/config.json" "$WORK/model/"
$AGO eval --ckpt "$WORK/model/checkpoint.pt" --data "$WORK/synth" --split val --out "$WORK/model/eval-val" \
    --readout "$READOUT_EVAL"
stamp

echo "== 5/6 export (parity-checked on the real nuScenes keyframe when ../shared is present)"
READOUT_GRID="$READOUT_GRID" bash "$REPO/scripts/export_default_bundle.sh" "$WORK/model" "$WORK/bundle"
stamp

if [ "$INSTALL" != 1 ]; then echo "done: bundle in $WORK/bundle (INSTALL=0: not copied into the package)"; exit 0; fi
echo "== 6/6 copy into $ASSETS, keep the model in $REPO/models/default"
mkdir -p "$ASSETS" "$REPO/models"
rm -rf "$REPO/models/default.new" && mkdir -p "$REPO/models/default.new/eval-val"
cp "$WORK/model/checkpoint.pt" "$WORK/model/log.jsonl" "$WORK/model/config.json" "$REPO/models/default.new/"
cp "$WORK/model/eval-val/metrics.json" "$REPO/models/default.new/eval-val/"
[ -f "$REPO/models/default/README.md" ] && cp "$REPO/models/default/README.md" "$REPO/models/default.new/"
rm -rf "$REPO/models/default" && mv "$REPO/models/default.new" "$REPO/models/default"
rm -rf "$ASSETS/default_bundle.new" && cp -r "$WORK/bundle" "$ASSETS/default_bundle.new"
rm -rf "$ASSETS/default_bundle" && mv "$ASSETS/default_bundle.new" "$ASSETS/default_bundle"

# Demo frame: six JPEGs named by camera + calib.json, from the first val frame of the synthetic city
# (never real nuScenes images: their licence forbids bundling them).
python - "$WORK/synth" "$ASSETS/demo_frame" <<'PY'
import sys, shutil
from pathlib import Path
import cv2
from ago_runtime.formats.calibration import save_calibration
from ago_runtime.formats.nuscenes import NuScenesDataset

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
stamp
echo "done: try  python -m ago_runtime demo"
