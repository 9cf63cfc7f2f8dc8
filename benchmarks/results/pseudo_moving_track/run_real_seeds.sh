#!/usr/bin/env bash
# after run_track.sh: the real scene with --moving track and, at the same commit, with --moving aggregate (the
# default); then a second seed of the 1500-step synthetic A/B for aggregate and track
set -x
cd /work/runs/track
while pgrep -f run_track.sh > /dev/null; do sleep 20; done
date
ago train-real /work/shared/data/nuscenes-scene /work/runs/track/tr_track --moving track > tr_track.log 2>&1
echo "train-real track rc=$?"
date
ago train-real /work/shared/data/nuscenes-scene /work/runs/track/tr_agg --moving aggregate > tr_agg.log 2>&1
echo "train-real aggregate rc=$?"
date
for r in agg tr; do
  if [ $r = agg ]; then P=/work/runs/defaultg/pseudo; else P=/work/runs/track/pseudo_tr; fi
  ago train --config /work/main/models/default/config.json --out /work/runs/track/train_${r}_s1 --set max_steps=1500 --set warmup_steps=200 --set seed=1 --set "pseudo=\"$P\"" > train_${r}_s1.log 2>&1
  echo "train $r seed 1 rc=$?"
  ago export /work/runs/track/train_${r}_s1/last.pt -o /work/runs/track/bundle_${r}_s1 --readout-grid 200x200x16 --train-bank-only > export_${r}_s1.log 2>&1
  echo "export rc=$?"
  (cd /work/main && python -m benchmarks.default_bundle_towns --towns /work/runs/fresh101 /work/runs/fresh202 /work/runs/fresh303 /work/runs/fresh404 --prior-data /work/runs/defaultg/synth --bundle /work/runs/track/bundle_${r}_s1 --out /work/runs/track/towns_${r}_s1.md) > towns_${r}_s1.log 2>&1
  echo "towns $r seed 1 rc=$?"
  date
done
