"""The two serial lines' framing, shared by the drivers and the device emulators.

Both controllers (the SDH2's joint controller and the DSACON32m) talk RS-232 at 115200 baud, 8N1:
a byte costs a start bit, 8 data bits and a stop bit on the wire.
"""

from typing import Final

BAUD: Final = 115_200
BITS_PER_BYTE: Final = 10  # 8N1
