"""The REST/WebSocket API in rooms: one router per area (docs/api.md is the contract).

:mod:`.deps` holds what every router asks for (the services, the token check), :mod:`.errors`
the error bodies and their documentation; ``sdh2svc.service.app`` assembles the routers.
"""
