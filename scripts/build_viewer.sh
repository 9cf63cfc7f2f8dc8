#!/usr/bin/env bash
# Rebuilds the 3-D viewer's library asset (development time only; the result is committed):
#   ago_runtime/assets/viewer/three_bundle.min.js   three.js core + OrbitControls, bundled and minified by esbuild
#   ago_runtime/assets/viewer/THREE_LICENSE          three.js's licence (MIT)
# npm packages are pinned; they are installed into a temporary folder, never into the repository.
# Usage: bash scripts/build_viewer.sh        (needs node + npm and the npm registry)
set -euo pipefail
THREE_VERSION=0.187.0
ESBUILD_VERSION=0.28.2
repo="$(cd "$(dirname "$0")/.." && pwd)"
dest="$repo/ago_runtime/assets/viewer"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
npm init -y >/dev/null
npm install --no-audit --no-fund --save-exact "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION" >/dev/null
# Only what ago_runtime/assets/viewer/viewer.js uses (esbuild drops the rest of three.js).
cat > entry.js <<'JS'
export {
  WebGLRenderer, Scene, PerspectiveCamera, InstancedMesh, InstancedBufferAttribute, BoxGeometry,
  BufferGeometry, Float32BufferAttribute, MeshBasicMaterial, LineSegments, LineBasicMaterial, Color,
  ColorManagement, LinearSRGBColorSpace, Matrix4, Vector2, Vector3, Raycaster,
} from "three";
export { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
JS
npx esbuild entry.js --bundle --minify --format=iife --global-name=THREE --target=es2020 --legal-comments=none \
  --outfile=three_bundle.min.js
mkdir -p "$dest"
{ echo "/* three.js $THREE_VERSION (MIT licence: THREE_LICENSE beside this file) + OrbitControls; bundled by esbuild $ESBUILD_VERSION with scripts/build_viewer.sh */"; cat three_bundle.min.js; } > "$dest/three_bundle.min.js"
cp node_modules/three/LICENSE "$dest/THREE_LICENSE"
echo "wrote $dest/three_bundle.min.js ($(wc -c < "$dest/three_bundle.min.js") bytes) and THREE_LICENSE"
