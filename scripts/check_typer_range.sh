#!/usr/bin/env bash
# The CLI's tests on typer versions other than the installed one, e.g. the two ends of pyproject.toml's range
# (`typer>=0.18,<0.30`: tested with 0.18.0, 0.26.0 and 0.29.2). Each version is installed without its
# dependencies into a throwaway folder put first on PYTHONPATH, so the environment's own typer is untouched
# (typer < 0.26 runs on the `click` package: it must be installed). Usage, from anywhere:
#   bash scripts/check_typer_range.sh 0.18.0 0.29.2
set -euo pipefail
cd "$(dirname "$0")/.."
versions=("$@")
[ ${#versions[@]} -gt 0 ] || versions=(0.18.0 0.29.2)
for version in "${versions[@]}"; do
  target="$(mktemp -d)"
  python -m pip install --quiet --no-deps --target "$target" "typer==$version"
  echo "== typer $version"
  PYTHONPATH="$target:$PWD" AGO_NO_PROGRESS=1 python -m pytest -q -p no:cacheprovider \
    tests/test_cli_options.py tests/test_bad_inputs.py tests/test_architecture.py
  rm -rf "$target"
done
