#!/usr/bin/env bash
# The previous and the remade default bundle on the real scene's held-out keyframes (real_chain's last 11, train_real's last 8), LiDAR measures.
# Usage: OLD_BUNDLE=DIR (the previous bundle, e.g. from `git worktree add /tmp/old d751bd9`) bash benchmarks/results/default_bundle_real_scene.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
SC=${SCENE:-../shared/data/nuscenes-scene}; O=${OUT:-work/default_bundle_real_scene}; mkdir -p $O
export AGO_NO_PROGRESS=1
for n in 11 8; do
  TOK=$(python -c "
import json,sys
s=json.load(open('$SC/v1.0-mini/sample.json')); s=sorted(s,key=lambda r:r['timestamp'])
print(' '.join('--sample '+r['token'] for r in s[-$n:]))")
  for name in old new; do
    B=$([ $name = old ] && echo "$OLD_BUNDLE" || echo ago_runtime/assets/default_bundle)
    [ -f $O/pred_${name}_$n/done ] || { rm -rf $O/pred_${name}_$n; python -m ago_runtime infer --images $SC --bundle $B $TOK --out $O/pred_${name}_$n --picture none > /dev/null && touch $O/pred_${name}_$n/done; }
    [ -f $O/metric_${name}_$n.json ] || python -m ago_runtime metric --pred $O/pred_${name}_$n --lidar $SC --allow-missing --json $O/metric_${name}_$n.json --md $O/metric_${name}_$n.md > /dev/null
  done
done
echo done
