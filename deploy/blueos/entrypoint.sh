#!/bin/sh
# Container entry point: the configuration lives in /etc/uwcam (a folder on the vehicle, bound
# by BlueOS), seeded with the simulated rig on first start; listening beyond loopback needs a
# token, so one is made on first start and kept beside the configuration.
set -eu
conf="${UWCAM_CONFIG_DIR:-/etc/uwcam}"
mkdir -p "$conf"
[ -f "$conf/uwcam.yaml" ] || cp "${UWCAM_DEFAULT_CONFIG:-/usr/share/uwcam/uwcam.yaml}" "$conf/uwcam.yaml"
if [ -z "${UWCAM_TOKEN:-}" ]; then
  if [ ! -s "$conf/token" ]; then
    (umask 077 && python -c 'import secrets; print(secrets.token_urlsafe(24))' > "$conf/token")
    echo "uwcam: new API token in $conf/token (needed for changes: lamp, settings, profiles)" >&2
  fi
  UWCAM_TOKEN=$(cat "$conf/token")
  export UWCAM_TOKEN
fi
exec uwcam run --config "$conf/uwcam.yaml" --host "${UWCAM_HOST:-0.0.0.0}" --port "${UWCAM_PORT:-6480}" "$@"
