#!/usr/bin/env bash
# Run the whole test suite (sets up .venv on first use). Arguments go to pytest; without any, the tests
# that compare generated data with a reference (marker generated_data) then run twice more, as they would
# on another processor: with NumPy's, OpenCV's and OpenBLAS's wider vector paths switched off, and on an
# emulated AVX2-only processor (qemu-user, installed here when missing), the only way to switch the ray
# caster's (open3d's Embree picks its paths from the processor). docs/session.md: what --seed promises.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
if [ $# -gt 0 ]; then
  exec python -m pytest -q "$@"
fi
python -m pytest -q

echo "[test] generated data again, with NumPy's, OpenCV's and OpenBLAS's wider vector paths off" >&2
NPY_DISABLE_CPU_FEATURES="X86_V3 X86_V4 AVX512_ICL AVX512_SPR" \
OPENCV_CPU_DISABLE="SSE4.1,SSE4.2,AVX,FP16,AVX2,AVX512-SKX" OPENCV_LOG_LEVEL=ERROR \
OPENBLAS_CORETYPE=Prescott \
  python -m pytest -q -p no:cacheprovider -m generated_data

if ! command -v qemu-x86_64 >/dev/null 2>&1 && [ "$(uname -m)" = x86_64 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "[test] installing qemu-user (an emulated processor for the ray caster's paths)" >&2
  { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq qemu-user; } >/dev/null 2>&1 || true
fi
if command -v qemu-x86_64 >/dev/null 2>&1 && [ "$(uname -m)" = x86_64 ]; then
  echo "[test] generated data again, on an emulated AVX2-only processor (qemu-x86_64 -cpu Haswell-v4)" >&2
  BASE_PY="$(python -c 'import os, sys; print(os.path.realpath(sys.executable))')"
  SITE="$(python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
  PYTHONPATH="$SITE:$ROOT/src" \
    qemu-x86_64 -cpu Haswell-v4 "$BASE_PY" -m pytest -q -p no:cacheprovider -m generated_data \
    tests/test_synth_reference.py 2> >(grep -v "TCG doesn't support" >&2)
else
  echo "[test] qemu-user not available: the ray caster's paths were not switched" >&2
fi
