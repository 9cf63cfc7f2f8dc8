#!/usr/bin/env bash
# after run_real_seeds.sh: keyframe at seed 1, then seed 2 of all three rules (1500 steps, the shipped config)
set -x
cd /work/runs/track
while pgrep -f run_real_seeds.sh > /dev/null; do sleep 20; done
for s_r in 1:kf 2:agg 2:tr 2:kf; do
  s=${s_r%%:*}; r=${s_r##*:}
  case $r in agg) P=/work/runs/defaultg/pseudo;; tr) P=/work/runs/track/pseudo_tr;; kf) P=/work/runs/moving/pseudo_kf;; esac
  date
  ago train --config /work/main/models/default/config.json --out /work/runs/track/train_${r}_s$s --set max_steps=1500 --set warmup_steps=200 --set seed=$s --set "pseudo=\"$P\"" > train_${r}_s$s.log 2>&1
  echo "train $r seed $s rc=$?"
  ago export /work/runs/track/train_${r}_s$s/last.pt -o /work/runs/track/bundle_${r}_s$s --readout-grid 200x200x16 --train-bank-only > export_${r}_s$s.log 2>&1
  echo "export rc=$?"
  (cd /work/main && python -m benchmarks.default_bundle_towns --towns /work/runs/fresh101 /work/runs/fresh202 /work/runs/fresh303 /work/runs/fresh404 --prior-data /work/runs/defaultg/synth --bundle /work/runs/track/bundle_${r}_s$s --out /work/runs/track/towns_${r}_s$s.md) > towns_${r}_s$s.log 2>&1
  echo "towns $r seed $s rc=$?"
done
date
