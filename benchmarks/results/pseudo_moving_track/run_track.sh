#!/usr/bin/env bash
# --moving track: pseudo-labels of the shipped model's training town, then the shipped config at 1500 steps (beside
# the committed A/B's aggregate and keyframe arms) and at 4000 steps (beside the shipped model), the four fresh towns
set -x
cd /work/runs/track
date
ago pseudo-labels --data /work/runs/defaultg/synth --out /work/runs/track/pseudo_tr --prompts cw --grid 100x100x16 --split train --segmenter sim --embedder sim --keyframes 10 --interval 1 --jobs 1 --carve grazing --moving track > pseudo_tr.log 2>&1
echo "pseudo rc=$?"
date
ago train --config /work/main/models/default/config.json --out /work/runs/track/train_tr --set max_steps=1500 --set warmup_steps=200 --set 'pseudo="/work/runs/track/pseudo_tr"' > train_tr.log 2>&1
echo "train 1500 rc=$?"
date
ago export /work/runs/track/train_tr/last.pt -o /work/runs/track/bundle_tr --readout-grid 200x200x16 --train-bank-only > export_tr.log 2>&1
echo "export rc=$?"
(cd /work/main && python -m benchmarks.default_bundle_towns --towns /work/runs/fresh101 /work/runs/fresh202 /work/runs/fresh303 /work/runs/fresh404 --prior-data /work/runs/defaultg/synth --bundle /work/runs/track/bundle_tr --out /work/runs/track/towns_tr.md) > towns_tr.log 2>&1
echo "towns 1500 rc=$?"
date
ago train --config /work/main/models/default/config.json --out /work/runs/track/train_tr4000 --set 'pseudo="/work/runs/track/pseudo_tr"' > train_tr4000.log 2>&1
echo "train 4000 rc=$?"
date
ago export /work/runs/track/train_tr4000/last.pt -o /work/runs/track/bundle_tr4000 --readout-grid 200x200x16 --train-bank-only > export_tr4000.log 2>&1
echo "export rc=$?"
(cd /work/main && python -m benchmarks.default_bundle_towns --towns /work/runs/fresh101 /work/runs/fresh202 /work/runs/fresh303 /work/runs/fresh404 --prior-data /work/runs/defaultg/synth --bundle /work/runs/track/bundle_tr4000 --out /work/runs/track/towns_tr4000.md) > towns_tr4000.log 2>&1
echo "towns 4000 rc=$?"
date
