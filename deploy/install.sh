#!/usr/bin/env bash
# Install uwcam into a virtual environment, .venv beside this checkout. Stock Debian, Ubuntu and
# Raspberry Pi OS refuse `pip install` into the system Python (PEP 668, "externally-managed-
# environment"), so uwcam always lives in its own environment.
#
#   bash deploy/install.sh          # the daemon with all its optional parts (reports, cluster, zenoh)
#   bash deploy/install.sh lean     # the daemon alone: ranging, recording, the page, MAVLink
#   bash deploy/install.sh test     # the daemon and everything its tests need (editable)
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-}"

if ! python3 -c 'import ensurepip, venv' 2>/dev/null; then
  # Debian ships venv's pip bootstrap in a package of its own.
  if [ "$(id -u)" -eq 0 ]; then SUDO=""; else SUDO="sudo"; fi
  echo "installing python3-venv (needed to create .venv)" >&2
  $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq python3-venv > /dev/null
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
export PIP_DISABLE_PIP_VERSION_CHECK=1
.venv/bin/python -m pip install --quiet --upgrade pip
if [ -z "$extras" ]; then
  # A user's install: a plain (non-editable) one, as the container image has it.
  .venv/bin/python -m pip install --quiet ".[cluster,reports,zenoh]"
elif [ "$extras" = "lean" ]; then
  .venv/bin/python -m pip install --quiet .
else
  # A developer's: editable, so that the tests run the checkout's code as it is edited.
  .venv/bin/python -m pip install --quiet -e ".[$extras]"
fi
# numba compiles the kernels once into its cache beside the sources: do it now (two minutes on
# 2 cores), so the first `uwcam run` ranges within seconds and no change of settings makes the
# frame loop stop to compile (16 s for smoothing before the transform).
.venv/bin/uwcam warmup
echo "uwcam installed in $(pwd)/.venv: run it as .venv/bin/uwcam" >&2
