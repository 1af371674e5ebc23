#!/usr/bin/env bash
# Re-vendor the 3D viewer library of the report from the npm registry:
#   three.js (core and OrbitControls) bundled once by esbuild into one classic script that sets the
#   global THREE, so that a report opened from file:// can load it (module scripts cannot load there).
# Writes three.viewer.min.js and LICENSE-three.txt beside this script. Needs node and npm.
# Usage: recon/report/vendor/build.sh            (versions below; edit them to upgrade)
set -euo pipefail
THREE_VERSION=0.187.0
ESBUILD_VERSION=0.28.2
here="$(cd "$(dirname "$0")" && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
npm init -y >/dev/null
npm install --no-audit --no-fund --save-exact "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION" >/dev/null
cat > entry.js <<'JS'
export {
  AmbientLight, BufferAttribute, BufferGeometry, Color, DirectionalLight, DoubleSide, Float32BufferAttribute,
  Mesh, MeshLambertMaterial, PerspectiveCamera, Points, PointsMaterial, SRGBColorSpace, Scene, Sphere, Vector3,
  WebGLRenderer,
} from "three";
export { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
export const VERSION = "THREE_VERSION_PLACEHOLDER";
JS
sed -i "s/THREE_VERSION_PLACEHOLDER/$THREE_VERSION/" entry.js
./node_modules/.bin/esbuild entry.js --bundle --format=iife --global-name=THREE --minify --target=es2020 \
  --legal-comments=eof --outfile="$here/three.viewer.min.js"
cp node_modules/three/LICENSE "$here/LICENSE-three.txt"
echo "three $THREE_VERSION bundled with esbuild $ESBUILD_VERSION: $(wc -c < "$here/three.viewer.min.js") bytes"
