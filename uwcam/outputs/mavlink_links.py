"""Links to the autopilot for the MAVLink output: UDP (``udpout:HOST:PORT``), TCP
(``tcp:HOST:PORT``) and serial devices, each with open/send/receive/close and one exception,
:class:`LinkDown`, for every way a link fails (the output then reconnects with backoff)."""

from __future__ import annotations

import select
import socket

from uwcam.config import MavlinkConfig, parse_mavlink_connection


class LinkDown(Exception):
    """The link to the autopilot failed; the output reconnects."""


class _Socket:
    def __init__(self, scheme: str, host: str, port: int) -> None:
        self.scheme, self.host, self.port = scheme, host, port
        self.sock: socket.socket | None = None

    def open(self) -> None:
        try:
            if self.scheme == "tcp":
                self.sock = socket.create_connection((self.host, self.port), timeout=2.0)
                self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            else:
                family, kind, proto, _, address = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_DGRAM)[0]
                self.sock = socket.socket(family, kind, proto)
                # Connected: the kernel reports "nothing listens there" (ICMP) as ECONNREFUSED,
                # and only the peer's replies (its heartbeats) are received.
                self.sock.connect(address)
            self.sock.settimeout(1.0)
        except OSError as exc:
            self.close()
            raise LinkDown(f"cannot reach {self.scheme}:{self.host}:{self.port}: {exc}") from None

    def send(self, data: bytes) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            if self.scheme == "udpout" and isinstance(exc, ConnectionRefusedError):
                raise LinkDown(f"nothing listens at udp {self.host}:{self.port} (connection refused)") from None
            raise LinkDown(f"sending to {self.scheme}:{self.host}:{self.port} failed: {exc}") from None

    def receive(self) -> bytes:
        """What has arrived, without waiting (b"" if nothing)."""
        data = b""
        try:
            while select.select([self.sock], [], [], 0)[0]:
                chunk = self.sock.recv(65536)
                if not chunk and self.scheme == "tcp":
                    raise LinkDown(f"tcp {self.host}:{self.port} closed the connection")
                data += chunk
                if len(data) > 1 << 20:
                    break
        except ConnectionRefusedError:
            # UDP: the kernel's report of an ICMP "port unreachable" for an earlier datagram.
            raise LinkDown(f"nothing listens at udp {self.host}:{self.port} (connection refused)" if self.scheme == "udpout"
                           else f"tcp {self.host}:{self.port} refused the connection") from None
        except OSError as exc:
            raise LinkDown(f"receiving from {self.scheme}:{self.host}:{self.port} failed: {exc}") from None
        return data

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class _Serial:
    def __init__(self, device: str, baud: int) -> None:
        self.device, self.baud = device, baud
        self.port = None

    def open(self) -> None:
        import serial

        try:
            self.port = serial.Serial(self.device, self.baud, timeout=0, write_timeout=1.0)
        except (serial.SerialException, OSError) as exc:
            raise LinkDown(f"cannot open {self.device}: {exc}") from None

    def send(self, data: bytes) -> None:
        import serial

        try:
            self.port.write(data)
        except (serial.SerialException, OSError) as exc:
            raise LinkDown(f"writing to {self.device} failed: {exc}") from None

    def receive(self) -> bytes:
        import serial

        try:
            return self.port.read(self.port.in_waiting or 0) if self.port.in_waiting else b""
        except (serial.SerialException, OSError) as exc:
            raise LinkDown(f"reading from {self.device} failed: {exc}") from None

    def close(self) -> None:
        from uwcam.drivers.serial_link import close_quietly

        close_quietly(self.port)
        self.port = None


def open_transport(config: MavlinkConfig):
    scheme, where, port = parse_mavlink_connection(config.connection)
    return _Serial(where, config.baud) if scheme == "serial" else _Socket(scheme, where, port)
