#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment in .venv with everything contact-viz needs.
# Sourced by scripts/demo.sh and scripts/test.sh; safe to run again (it is a no-op when up to date).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
PY="${PYTHON:-python3.11}"
command -v "$PY" >/dev/null 2>&1 || PY=python3

# open3d needs Debian's libusb-1.0 at import time.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "[bootstrap] installing libusb-1.0-0 (needed by open3d)" >&2
  $SUDO apt-get update -qq >&2
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >&2
fi

# The patch's compiled kernels (src/contact_viz/geometry/_patch_kernels.pyx) are built at install time.
if ! command -v cc >/dev/null 2>&1 && ! command -v gcc >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "[bootstrap] installing gcc (builds the patch's compiled kernels)" >&2
  $SUDO apt-get update -qq >&2
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq gcc >&2
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "[bootstrap] creating $VENV" >&2
  "$PY" -m venv "$VENV"
fi

# Re-install only when the build inputs changed since the last successful install (the compiled
# kernels of contact_viz.patch are built by that install, from setup.py and the .pyx file).
STAMP="$VENV/.contact-viz-installed"
WANT="$(cat "$ROOT/pyproject.toml" "$ROOT/setup.py" "$ROOT"/src/contact_viz/*/*.pyx | sha256sum | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  echo "[bootstrap] installing packages into $VENV (first run takes about a minute)" >&2
  # The CPU build of torch first: a bare `torch` requirement would pull several GB of CUDA packages.
  "$VENV/bin/pip" install -q torch==2.13.0 2>&1 | grep -v 'is ignored' >&2 || true
  "$VENV/bin/python" -c "import torch" 
  "$VENV/bin/pip" install -q -e "$ROOT[test]" 2>&1 | grep -v 'is ignored' >&2 || true
  "$VENV/bin/python" -c "import contact_viz.geometry._patch_kernels, open3d, rerun, cv2"
  echo "$WANT" > "$STAMP"
fi
# Byte-compile the package once here (a no-op when up to date): where PYTHONDONTWRITEBYTECODE is
# set, as on CI machines, every command would otherwise compile it again at start-up (~40 ms).
"$VENV/bin/python" -m compileall -q "$ROOT/src/contact_viz" >/dev/null
export PATH="$VENV/bin:$PATH"
