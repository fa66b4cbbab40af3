#!/usr/bin/env bash
# Install everything mitsuba-p3 needs on a fresh Debian/Ubuntu machine:
#   1. a libLLVM that Dr.Jit's LLVM backend can use (Debian's libllvm19; LLVM 15 aborts),
#   2. the Python package, editable, with its test extras (and bpy, for the Cycles renderer, on Python 3.11).
# Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

has_llvm() { "$PYTHON" -c "import sys; sys.path.insert(0, '.'); from mitsuba_p3.backend import find_llvm; find_llvm()" 2>/dev/null; }

if ! has_llvm; then
  echo "setup: installing libllvm19 for Dr.Jit (no usable libLLVM >= 16 found)"
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
  has_llvm || { echo "setup: libllvm19 did not give a usable libLLVM; see 'mitsuba-p3 doctor'" >&2; exit 1; }
fi

# -I: the import must come from the installed package (this clone), not from the working directory
if ! "$PYTHON" -I -c "import mitsuba_p3.cli, pytest, os, sys; sys.exit(os.path.realpath(mitsuba_p3.__file__) != os.path.realpath('mitsuba_p3/__init__.py'))" 2>/dev/null || [ pyproject.toml -nt .setup-done ]; then
  echo "setup: installing the mitsuba-p3 package and its dependencies"
  # the blender extra (the Cycles benchmark renderer, and its tests) where bpy exists: Python 3.11
  "$PYTHON" -m pip install -q --disable-pip-version-check -e ".[test,blender]"
  touch .setup-done
fi
"$PYTHON" -m mitsuba_p3.cli doctor >/dev/null
echo "setup: ready"
