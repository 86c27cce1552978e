#!/usr/bin/env bash
# Install the ShadowCorr runtime (library + service + client, no test tools) into a
# virtual environment.  The Dockerfile runs exactly this script; a test runs it too.
#   install-runtime.sh VENV_DIR
# TORCH_INDEX_URL, when set, is the wheel index torch comes from, e.g. PyTorch's CPU
# index (https://download.pytorch.org/whl/cpu) or a CUDA one (.../whl/cu124).  Unset,
# pip's own configuration decides.
set -euo pipefail
venv=${1:?usage: install-runtime.sh VENV_DIR}
src=$(cd "$(dirname "$0")/.." && pwd)
python3 -m venv "$venv"
"$venv/bin/python" -m pip install --no-cache-dir --disable-pip-version-check -q \
  ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"} "torch>=2.4,<2.14"
"$venv/bin/python" -m pip install --no-cache-dir --disable-pip-version-check -q "$src"
