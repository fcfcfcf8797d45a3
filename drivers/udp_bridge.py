"""A serial port shared over UDP, the way BlueOS's ping service shares a Ping sonar.

Every datagram a client sends goes to the serial device; everything the device sends goes to
every client heard from in the last ``client_timeout_s``. uwcam's ``ping1d`` driver reads such
a bridge with ``port: udp:HOST:PORT``. Use it to share a sonar without BlueOS, and in the
tests, where it bridges a simulated Ping1D on a pseudo-terminal::

    python -m uwcam.drivers.udp_bridge /dev/ttyUSB0 --port 9090
"""

from __future__ import annotations

import argparse
import select
import socket
import time

import serial

from uwcam.drivers.threads import SelectThread
from uwcam.drivers.serial_link import close_quietly


class SerialUdpBridge:
    """Bridges ``device`` (a serial port) to a UDP port on ``host``; ``port`` 0 picks a free one."""

    def __init__(self, device: str, baud: int = 115200, host: str = "127.0.0.1", port: int = 0,
                 client_timeout_s: float = 30.0) -> None:
        self.device, self.baud = device, baud
        self.host, self.port = host, port
        self.client_timeout_s = client_timeout_s
        self.clients: dict[tuple, float] = {}
        self.silent = False
        """While True every datagram and every byte from the device is dropped (a stalled bridge)."""
        self._sock: socket.socket | None = None
        self._serial: serial.Serial | None = None
        self._loop = SelectThread(self._run, "udp-bridge")

    @property
    def address(self) -> str:
        return f"udp:{self.host}:{self.port}"

    def start(self) -> "SerialUdpBridge":
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((self.host, self.port))
        self.port = self._sock.getsockname()[1]
        self._loop.start()
        return self

    def stop(self) -> None:
        """Close the UDP port (clients then get "connection refused") and the serial port."""
        self._loop.stop()
        if self._sock is not None:
            self._sock.close()
        self._close_serial()

    def __enter__(self) -> "SerialUdpBridge":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _close_serial(self) -> None:
        close_quietly(self._serial)
        self._serial = None

    def _open_serial(self) -> serial.Serial | None:
        if self._serial is None:
            try:
                self._serial = serial.Serial(self.device, self.baud, timeout=0)
            except (serial.SerialException, OSError):
                return None  # the device is away; tried again on the next wake-up
        return self._serial

    def _run(self) -> None:
        while True:
            port = self._open_serial()
            fds = [self._loop.stop_fd, self._sock] + ([port.fileno()] if port is not None else [])
            ready, _, _ = select.select(fds, [], [], 0.2 if port is None else None)
            if self._loop.stop_fd in ready:
                return
            if self._sock in ready:
                data, client = self._sock.recvfrom(65536)
                if not self.silent:
                    self.clients[client] = time.monotonic()
                    self._to_device(data)
            if port is not None and port.fileno() in ready:
                self._from_device(port)

    def _to_device(self, data: bytes) -> None:
        port = self._open_serial()
        if port is None:
            return
        try:
            port.write(data)
        except (serial.SerialException, OSError):
            self._close_serial()

    def _from_device(self, port: serial.Serial) -> None:
        try:
            data = port.read(4096)
        except (serial.SerialException, OSError):
            self._close_serial()
            return
        if not data:  # readable but empty: the other end of the line went away
            self._close_serial()
            return
        if self.silent:
            return
        now = time.monotonic()
        for client, seen in list(self.clients.items()):
            if now - seen > self.client_timeout_s:
                del self.clients[client]
                continue
            try:
                self._sock.sendto(data, client)
            except OSError:
                del self.clients[client]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Share a serial device (e.g. a Ping sonar) over UDP.")
    parser.add_argument("device")
    parser.add_argument("--baud", type=int, default=115200)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=9090)
    args = parser.parse_args(argv)
    bridge = SerialUdpBridge(args.device, args.baud, args.host, args.port).start()
    print(f"bridging {args.device} at {bridge.address}; Ctrl-C stops")
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        bridge.stop()


if __name__ == "__main__":
    main()
