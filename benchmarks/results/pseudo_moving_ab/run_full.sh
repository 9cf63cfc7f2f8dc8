#!/usr/bin/env bash
# the shipped model's full configuration (4000 steps, its own warm-up) on --moving keyframe pseudo-labels, then the
# four fresh towns for it and, side by side, for the shipped bundle
set -x
cd /work/runs/moving
date
ago train --config /work/main/models/default/config.json --out /work/runs/moving/train_kf4000 --set 'pseudo="/work/runs/moving/pseudo_kf"' > train_kf4000.log 2>&1
echo "rc=$?"
date
ago export /work/runs/moving/train_kf4000/last.pt -o /work/runs/moving/bundle_kf4000 --readout-grid 200x200x16 --train-bank-only > export_kf4000.log 2>&1
echo "export rc=$?"
date
(cd /work/main && python -m benchmarks.default_bundle_towns --towns /work/runs/fresh101 /work/runs/fresh202 /work/runs/fresh303 /work/runs/fresh404 --prior-data /work/runs/defaultg/synth --bundle /work/runs/moving/bundle_kf4000 --out /work/runs/moving/towns_kf4000.md) > towns_kf4000.log 2>&1
echo "towns kf4000 rc=$?"
(cd /work/main && python -m benchmarks.default_bundle_towns --towns /work/runs/fresh101 /work/runs/fresh202 /work/runs/fresh303 /work/runs/fresh404 --prior-data /work/runs/defaultg/synth --bundle /work/main/ago_runtime/assets/default_bundle --out /work/runs/moving/towns_shipped.md) > towns_shipped.log 2>&1
echo "towns shipped rc=$?"
date
