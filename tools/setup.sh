#!/usr/bin/env bash
# One idempotent set-up for a Debian machine: system packages, .venv, pinned Python deps.
# Fast when already done: each step checks a stamp (the hash of what it installs).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=$ROOT/.venv
PY=${PYTHON:-python3}
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"

# 1. Debian packages: libLLVM >= 16 for Dr.Jit's LLVM backend; Mesa EGL for the OpenGL check.
APT_PKGS="libllvm19 libegl1 libegl-mesa0 libgl1-mesa-dri"
missing=""
for p in $APT_PKGS; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  echo "setup: installing Debian packages:$missing"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
fi

# 2. Virtual environment.
if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV"
  "$PY" -m venv "$VENV"
fi

# 3. Pinned dependencies. torch is asked for as the CPU build explicitly (+cpu local version);
#    set TORCH_FIND_LINKS or PIP_EXTRA_INDEX_URL to where a CPU wheel lives if pip cannot find one.
stamp=$VENV/.shadowopt-deps
want=$(cat requirements.lock pyproject.toml | sha1sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "setup: installing pinned Python dependencies (first time: a few minutes)"
  "$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
  links=()
  [ -n "${TORCH_FIND_LINKS:-}" ] && links=(--find-links "$TORCH_FIND_LINKS")
  [ -d /opt/wheels ] && links+=(--find-links /opt/wheels)
  "$VENV/bin/python" -m pip install -q "${links[@]}" "torch==2.13.0+cpu"
  "$VENV/bin/python" -m pip install -q -r requirements.lock
  "$VENV/bin/python" -m pip install -q --no-deps -e ".[server,dev]"
  echo "$want" > "$stamp"
fi
