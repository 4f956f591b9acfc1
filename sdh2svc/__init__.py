"""sdh2svc — tactile in-hand rolling on a SCHUNK SDH2 hand.

Layers (imports point down only): ``model`` and ``protocol`` (pure) → ``bus`` and ``sim``
(asyncio links, device emulators) → ``control`` (rolling step + runner) → ``service``.
"""

__version__ = "0.1.0"
