#!/usr/bin/env bash
# Set up difftex in ./.venv: CPU torch pinned by constraints.txt (an unpinned torch pulls a
# multi-GB CUDA build), the package in editable mode, and the perceptual-metric weight files.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -c constraints.txt torch==2.13.0
.venv/bin/python -m pip install -q -c constraints.txt -e ".[test]"
# These two wheels carry the LPIPS / ST-LPIPS weight files; their code needs torchvision, so they
# are installed without dependencies and difftex loads only their weights (difftex/perceptual.py).
.venv/bin/python -m pip install -q --no-deps stlpips-pytorch==0.0.2 lpips==0.1.4
echo "difftex installed in $(pwd)/.venv"
