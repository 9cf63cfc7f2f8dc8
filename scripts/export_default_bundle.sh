#!/usr/bin/env bash
# Export the default bundle from a kept model folder (checkpoint.pt, log.jsonl, config.json, eval-val/metrics.json;
# scripts/make_default_bundle.sh writes one and the repository keeps the shipped bundle's in models/default/).
# With no arguments it re-makes the shipped bundle in ago_runtime/assets/default_bundle from models/default:
# what a bundle format change runs, with no training. Usage:
#   bash scripts/export_default_bundle.sh [MODEL_DIR [BUNDLE_DIR]]
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
MODEL="${1:-$REPO/models/default}"
OUT="${2:-$REPO/ago_runtime/assets/default_bundle}"
READOUT_GRID="${READOUT_GRID-200x200x16}"
READOUT=()
[ -n "$READOUT_GRID" ] && READOUT=(--readout-grid "$READOUT_GRID")
[ -f "$MODEL/checkpoint.pt" ] || { echo "error: $MODEL/checkpoint.pt: no kept checkpoint there" >&2; exit 2; }

# into a new folder beside OUT, renamed over it only when the export (parity check included) succeeded
rm -rf "$OUT.new"
python -m ago_runtime export "$MODEL/checkpoint.pt" -o "$OUT.new" "${READOUT[@]}" \
    --card-note "a demonstration model trained by scripts/make_default_bundle.sh on the SYNTHETIC world only"
rm -rf "$OUT" && mv "$OUT.new" "$OUT"
echo "bundle: $OUT (from $MODEL/checkpoint.pt)"
