#!/usr/bin/env bash
# One command sets ShadowCorr up and runs the main job on the embedded sample scene:
#   1. system packages for the optional synthetic-data renderer (only as root with apt;
#      the library, CLI and service need none),
#   2. a virtual environment .venv with the project, its tests', the generator's, Ray's, the
#      documentation's and Rerun's (exports) packages,
#   3. convert the sample (examples/ue_sample, Unreal layout) and label its segments.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  # Offscreen OpenGL (EGL on Mesa's software rasteriser) lets `shadowcorr synth` render
  # depth and masks with MuJoCo; without it the generator falls back to its numpy renderer.
  if ! (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 >/dev/null); then
    echo "warning: could not install the EGL packages; 'shadowcorr synth' will use its slower numpy renderer" >&2
  fi
fi

"$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[dev,synth,ray,docs,viz]"

mkdir -p out
.venv/bin/shadowcorr convert ue examples/ue_sample --set 2001 --cameras 0,2,4,6 --out out/sample_bundle
.venv/bin/shadowcorr correspond out/sample_bundle --out out/sample_result.json
