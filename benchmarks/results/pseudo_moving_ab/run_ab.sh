#!/usr/bin/env bash
# A/B: the shipped model's training config, 1500 steps, on the aggregate pseudo-labels (A) and on --moving keyframe ones (B)
set -x
cd /work/runs/moving
date
ago train --config /work/main/models/default/config.json --out /work/runs/moving/train_agg --set max_steps=1500 --set warmup_steps=200 > train_agg.log 2>&1
echo "rc=$?"
date
ago train --config /work/main/models/default/config.json --out /work/runs/moving/train_kf --set max_steps=1500 --set warmup_steps=200 --set 'pseudo="/work/runs/moving/pseudo_kf"' > train_kf.log 2>&1
echo "rc=$?"
date
for r in agg kf; do
  ago export /work/runs/moving/train_$r/last.pt -o /work/runs/moving/bundle_$r --readout-grid 200x200x16 --train-bank-only > export_$r.log 2>&1
  echo "export $r rc=$?"
done
date
for r in agg kf; do
  (cd /work/main && python -m benchmarks.default_bundle_towns --towns /work/runs/fresh101 /work/runs/fresh202 /work/runs/fresh303 /work/runs/fresh404 --prior-data /work/runs/defaultg/synth --bundle /work/runs/moving/bundle_$r --out /work/runs/moving/towns_$r.md) > towns_$r.log 2>&1
  echo "towns $r rc=$?"
done
date
