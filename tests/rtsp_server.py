"""A real RTSP server for the stream driver's tests: GStreamer's gst-rtsp-server streaming frames
from a .npy file (N, H, W, 3 uint8 RGB, looped) as H.264 (x264, as mavlink-camera-manager's
software encoder) or MJPEG over RTP.

    python tests/rtsp_server.py PORT FRAMES.npy [h264|mjpeg] [BITRATE_KBPS]

Prints "ready rtsp://127.0.0.1:PORT/cam" once it listens; runs until killed.
"""

from __future__ import annotations

import sys

import gi
import numpy as np

gi.require_version("Gst", "1.0")
gi.require_version("GstRtspServer", "1.0")
from gi.repository import GLib, Gst, GstRtspServer  # noqa: E402

FPS = 15


def main() -> int:
    port, path = int(sys.argv[1]), sys.argv[2]
    codec = sys.argv[3] if len(sys.argv) > 3 else "h264"
    bitrate = int(sys.argv[4]) if len(sys.argv) > 4 else 4000
    frames = np.load(path)
    n, h, w, _ = frames.shape
    Gst.init(None)
    encoder = (f"x264enc tune=zerolatency speed-preset=ultrafast bitrate={bitrate} key-int-max={FPS} bframes=0 "
               "! rtph264pay name=pay0 pt=96 config-interval=1" if codec == "h264"
               else "jpegenc quality=90 ! rtpjpegpay name=pay0 pt=26")
    # H.264 in limited-range BT.601 YUV (as encoders send it); MJPEG in full-range JFIF YUV (as
    # cameras send it): the colorimetry string is range:matrix:transfer:primaries.
    yuv = "video/x-raw,format=I420" + (",colorimetry=1:4:0:0" if codec == "mjpeg" else "")
    launch = (f"( appsrc name=src is-live=true format=time do-timestamp=false "
              f"caps=video/x-raw,format=RGB,width={w},height={h},framerate={FPS}/1 "
              f"! videoconvert ! {yuv} ! {encoder} )")
    factory = GstRtspServer.RTSPMediaFactory()
    factory.set_launch(launch)
    factory.set_shared(True)
    state = {"i": 0}

    def need_data(src, _length):
        frame = frames[state["i"] % n]
        buf = Gst.Buffer.new_wrapped(frame.tobytes())
        buf.pts = state["i"] * Gst.SECOND // FPS
        buf.duration = Gst.SECOND // FPS
        state["i"] += 1
        src.emit("push-buffer", buf)

    def configure(_factory, media):
        src = media.get_element().get_child_by_name("src")
        src.connect("need-data", need_data)

    factory.connect("media-configure", configure)
    server = GstRtspServer.RTSPServer()
    server.set_address("127.0.0.1")
    server.set_service(str(port))
    server.get_mount_points().add_factory("/cam", factory)
    if server.attach(None) == 0:
        print(f"cannot listen on port {port}", flush=True)
        return 1
    print(f"ready rtsp://127.0.0.1:{port}/cam", flush=True)
    GLib.MainLoop().run()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
