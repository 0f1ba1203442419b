#!/usr/bin/env bash
# Set up difftex in ./.venv: the registry's standard torch + torchvision pair (pinned together in
# constraints.txt; CUDA builds that also run on a CPU), piq (SSIM cross-checks and classic LPIPS,
# whose weight files are read from the torch hub cache, docs/metrics.md), the package in editable
# mode, and ST-LPIPS (stlpips-pytorch, weights in the wheel). The lpips package is not installed.
#
# CPU-only torch instead (no CUDA libraries: several GB smaller): install it first, then run this script with
#   TORCH_INDEX=https://download.pytorch.org/whl/cpu bash scripts/install.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
# Large wheels (torch's CUDA libraries, pymeshlab) come over a link that drops: pip resumes a broken
# download (--resume-retries, pip >= 25.1, hence the upgrade first), and a whole install that still
# fails is tried again, up to three times, keeping what it already installed. pip reports a full disk
# as "Connection interrupted" too (seen here), so its cache is off: the CUDA wheels would otherwise be
# stored twice, about 4 GB more than the 6.8 GB the environment takes.
export PIP_NO_CACHE_DIR=1
retry() {
  local attempt
  for attempt in 1 2 3; do
    "$@" && return 0
    [ "$attempt" = 3 ] || { echo "note: install step failed (attempt $attempt of 3), retrying: $*" >&2; sleep 5; }
  done
  return 1
}
retry .venv/bin/python -m pip install -q --upgrade pip
export PIP_RESUME_RETRIES=20 PIP_RETRIES=10
PIP=(retry .venv/bin/python -m pip install -q -c constraints.txt)
if [ -n "${TORCH_INDEX:-}" ]; then
  "${PIP[@]}" --index-url "$TORCH_INDEX" torch torchvision
fi
"${PIP[@]}" torch torchvision piq
# "perceptual": ST-LPIPS (stlpips-pytorch), which difftex.evaluation.metrics calls directly, with the
# imports it needs but does not declare (IPython, torchsummary).
"${PIP[@]}" -e ".[test,perceptual]"
# Optional: Mitsuba's fast llvm_ad_rgb variant (synthetic scenes) needs Debian's libllvm19;
# without it difftex synth falls back to scalar_rgb, about 2x slower.
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! ldconfig -p 2>/dev/null | grep -q libLLVM.so.19; then
  (apt-get install -y -qq libllvm19 >/dev/null 2>&1 || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libllvm19 >/dev/null 2>&1; }) \
    || echo "note: libllvm19 not installed; Mitsuba will use scalar_rgb"
fi
# The MeshLab peer (pymeshlab, installed above with the package) needs an OpenGL context and Qt's
# platform plugins: Debian's xvfb + xauth (xvfb-run) and libqt5gui5. texrecon, the other peer, is
# built separately: ../shared/peers/build_texrecon.sh (README, "Peers").
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! { command -v xvfb-run >/dev/null && command -v xauth >/dev/null && dpkg -s libqt5gui5 >/dev/null 2>&1; }; then
  (apt-get install -y -qq xvfb xauth libqt5gui5 >/dev/null 2>&1 || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq xvfb xauth libqt5gui5 >/dev/null 2>&1; }) \
    || echo "note: xvfb/xauth/libqt5gui5 not installed; the MeshLab peer will be reported as unavailable"
fi
.venv/bin/python -c "import torch, torchvision, piq; print(f'difftex installed in $(pwd)/.venv: torch {torch.__version__}, torchvision {torchvision.__version__}, piq {piq.__version__}, CUDA ' + ('available' if torch.cuda.is_available() else 'not available (CPU)'))"
