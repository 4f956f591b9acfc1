"""``unix:///path/to/socket``: a serial port over a Unix-domain stream socket.

The same byte stream as ``socket://host:port``, but delivered synchronously by the kernel, which
is what the simulator's fast mode (a virtual clock) needs.
"""

from __future__ import annotations

import socket
import urllib.parse

from serial.serialutil import SerialException
from serial.urlhandler import protocol_socket


class Serial(protocol_socket.Serial):
    """pyserial's socket port, connected to a Unix-domain socket path instead of host:port."""

    def open(self) -> None:
        url = self.portstr
        if url is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        path = self.from_url(url)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.connect(path)
        except OSError as e:
            sock.close()
            raise SerialException(f"Could not open port {self.portstr}: {e}") from None
        sock.setblocking(False)
        self._socket = sock
        self.logger = None
        self.is_open = True
        self.reset_input_buffer()
        self.reset_output_buffer()

    def from_url(self, url: str) -> str:  # type: ignore[override]
        """``unix:///tmp/x.sock`` → ``/tmp/x.sock``."""
        parts = urllib.parse.urlsplit(url)
        if parts.scheme != "unix" or not parts.path:
            raise SerialException(f"expected a URL like unix:///path/to/socket, got {url!r}")
        return parts.path
