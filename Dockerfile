# uwcam as a BlueOS extension (also runs as a plain container).
#
#   docker buildx build --platform linux/amd64,linux/arm64,linux/arm/v7 -t OWNER/blueos-uwcam:0.1.0 --push .
#
# Two stages: every Python dependency is built into a wheel in the first (compilers, headers),
# the second installs only the wheels and the run-time libraries. PYTHON_IMAGE can name a
# compatible local image where Docker Hub cannot be reached.
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
ARG TARGETARCH
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1
# PyGObject (for Aravis: GigE Vision and USB3 Vision cameras) has no wheels and compiles here.
RUN apt-get update \
 && apt-get install -y --no-install-recommends build-essential pkg-config libgirepository1.0-dev libcairo2-dev \
 && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY pyproject.toml README.md ./
COPY uwcam ./uwcam
COPY drivers ./drivers
COPY calibration_rigs ./calibration_rigs
COPY deploy/blueos ./deploy/blueos
# 32-bit ARM: numpy, OpenCV and pydantic-core come from piwheels (Raspberry Pi builds for this
# Debian release); numba, harvesters and pymavlink's fastcrc are left out (see requirements.py).
RUN set -eu; \
    extra=""; if [ "$TARGETARCH" = "arm" ]; then extra="--extra-index-url https://www.piwheels.org/simple"; fi; \
    python deploy/blueos/requirements.py "$TARGETARCH" > /tmp/requirements.txt; \
    pip wheel --wheel-dir /wheels $extra -r /tmp/requirements.txt "PyGObject<3.51"; \
    if [ "$TARGETARCH" = "arm" ]; then pip wheel --no-deps --wheel-dir /wheels "pymavlink>=2.4.40"; fi; \
    pip wheel --no-deps --wheel-dir /wheels .

FROM ${PYTHON_IMAGE}
# numba's parallel kernels run in more than one thread (frame loop, simulated camera): its only
# thread-safe layer available here is OpenMP (libgomp1). Without it numba falls back to its
# workqueue layer, which aborts the process on concurrent use; "threadsafe" makes that an error.
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1 PYTHONUNBUFFERED=1 NUMBA_THREADING_LAYER=threadsafe
RUN apt-get update \
 && apt-get install -y --no-install-recommends gir1.2-aravis-0.8 libgirepository-1.0-1 libcairo2 libgomp1 \
 && rm -rf /var/lib/apt/lists/*
# Every wheel was resolved in the build stage: install them as they are, without an index.
RUN --mount=type=bind,from=build,source=/wheels,target=/wheels pip install --no-deps /wheels/*.whl
COPY deploy/blueos/uwcam.yaml /usr/share/uwcam/uwcam.yaml
COPY deploy/blueos/entrypoint.sh /usr/local/bin/uwcam-entrypoint
# 6480: no BlueOS service uses it (BlueOS's own services and its MAVLink inspector's :8080; docs/blueos.md).
EXPOSE 6480
HEALTHCHECK --interval=30s --timeout=5s --start-period=120s \
  CMD python -c "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/api/v1/status' % os.environ.get('UWCAM_PORT', '6480'), timeout=4)"
ENTRYPOINT ["/usr/local/bin/uwcam-entrypoint"]

# BlueOS extension metadata (read by BlueOS's extension manager and the extensions store).
# Host networking: GigE Vision discovery is UDP broadcast, and the Ping and MAVLink endpoints
# of BlueOS listen on the vehicle's loopback. Privileged with /dev bound: serial lamps,
# USB cameras and sonars, found again after a re-plug. The configuration folder is kept on the vehicle.
ARG REPO=uwcam/uwcam
LABEL version="0.1.0"
LABEL permissions='{\
  "ExposedPorts": {"6480/tcp": {}},\
  "HostConfig": {\
    "NetworkMode": "host",\
    "Privileged": true,\
    "Binds": [\
      "/dev:/dev",\
      "/run/udev:/run/udev:ro",\
      "/usr/blueos/extensions/uwcam:/etc/uwcam"\
    ],\
    "RestartPolicy": {"Name": "unless-stopped"}\
  }\
}'
LABEL authors='[\
  {"name": "uwcam developers", "email": "uwcam@users.noreply.github.com"}\
]'
LABEL company='{\
  "about": "Range from colour: per-pixel range maps from an underwater camera and its lamp",\
  "name": "uwcam",\
  "email": "uwcam@users.noreply.github.com"\
}'
LABEL readme="https://raw.githubusercontent.com/${REPO}/{tag}/README.md"
LABEL links="{\"website\": \"https://github.com/${REPO}\", \"source\": \"https://github.com/${REPO}\", \"support\": \"https://github.com/${REPO}/issues\", \"documentation\": \"https://github.com/${REPO}#on-the-vehicle-ardusub-the-ping-through-blueos-a-blueos-extension\"}"
LABEL type="device-integration"
LABEL tags='["camera", "rangefinder", "sonar", "mavlink", "navigation", "data-collection"]'
LABEL requirements="core >= 1.1"
