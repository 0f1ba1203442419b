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
# Optional: Mitsuba's fast llvm_ad_rgb variant (synthetic scenes) needs Debian's libllvm19;
# without it difftex synth falls back to scalar_rgb, about 2x slower.
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! ldconfig -p 2>/dev/null | grep -q libLLVM.so.19; then
  (apt-get install -y -qq libllvm19 >/dev/null 2>&1 || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libllvm19 >/dev/null 2>&1; }) \
    || echo "note: libllvm19 not installed; Mitsuba will use scalar_rgb"
fi
echo "difftex installed in $(pwd)/.venv"
