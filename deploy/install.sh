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
# uv installs the same packages from the same index as pip, in seconds where pip takes one to two
# minutes; where uv cannot be had or fails, pip does it. uv reads its own settings: pip's index
# settings, where they are set, are handed on.
if [ -n "${PIP_INDEX_URL:-}" ]; then export UV_INDEX_URL="${UV_INDEX_URL:-$PIP_INDEX_URL}"; fi
if [ -n "${PIP_EXTRA_INDEX_URL:-}" ]; then export UV_EXTRA_INDEX_URL="${UV_EXTRA_INDEX_URL:-$PIP_EXTRA_INDEX_URL}"; fi
if [ -n "${PIP_FIND_LINKS:-}" ]; then export UV_FIND_LINKS="${UV_FIND_LINKS:-$PIP_FIND_LINKS}"; fi
# The system's certificates, as pip uses them (uv's own set lacks a proxy's or a company's CA).
export UV_SYSTEM_CERTS="${UV_SYSTEM_CERTS:-1}" UV_NATIVE_TLS="${UV_NATIVE_TLS:-1}"
.venv/bin/python -m pip install --quiet uv > /dev/null 2>&1 || true
install() {
  if [ -x .venv/bin/uv ] && .venv/bin/uv pip install --quiet --python .venv/bin/python "$@"; then
    return
  fi
  echo "installing with pip instead of uv" >&2
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet "$@"
}
if [ -z "$extras" ]; then
  # A user's install: a plain (non-editable) one, as the container image has it.
  install ".[cluster,reports,zenoh]"
elif [ "$extras" = "lean" ]; then
  install .
else
  # A developer's: editable, so that the tests run the checkout's code as it is edited.
  install -e ".[$extras]"
  # numba compiles the kernels into its cache beside the sources: all of them now (two minutes
  # on 2 cores), so that no test waits on a compilation. A user's install does not wait for it:
  # `uwcam run` compiles what its first frames need and starts `uwcam warmup` for the rest in the
  # background, once (README, "Set-up").
  .venv/bin/uwcam warmup
fi
echo "uwcam installed in $(pwd)/.venv: run it as .venv/bin/uwcam" >&2
