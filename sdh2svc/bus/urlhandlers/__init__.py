"""pyserial URL handlers of our own: ``unix:///path`` (a Unix-domain stream socket).

Registered with pyserial by :func:`register` (importing :mod:`sdh2svc.bus` does it), so
``serial.serial_for_url("unix:///tmp/dsa.sock")`` — and therefore pyserial-asyncio — opens it
like any other port.
"""

from __future__ import annotations

import serial

PACKAGE = __name__


def register() -> None:
    """Let pyserial find the handlers in this package (idempotent)."""
    if PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(PACKAGE)
