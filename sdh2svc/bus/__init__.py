"""asyncio drivers of the hand's two serial links (any pyserial URL or device path).

Importing this package registers our pyserial URL handlers (``unix:///path``).
"""

from sdh2svc.bus.urlhandlers import register as _register_url_handlers

_register_url_handlers()
