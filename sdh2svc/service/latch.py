"""The e-stop latch another program writes to the run database while this one drives the hand.

``sdh2svc estop --latch`` writes the latch to the database; a restart re-applies it. A service
or a real-hand ``sdh2svc run`` keeping its runs in that database also reads it while it runs:
within :data:`LATCH_POLL_S` of the write it stops its hand, then says so in the database
(:meth:`~sdh2svc.service.store.RunStore.took_estop`), which is what the command waits for.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import sqlite3
from collections.abc import Callable

from sdh2svc.bus.joint import JointLink
from sdh2svc.service.store import RunStore

log = logging.getLogger(__name__)

LATCH_POLL_S = 0.5  # how often the database is read: the stop comes at most this much later
TAKE_WAIT_S = 5.0  # how long `estop --latch` waits for a program to say it stopped its hand


def _never() -> bool:
    return False


async def latched_elsewhere(
    store: RunStore, joints: JointLink, held: Callable[[], bool] = _never
) -> dict[str, str]:
    """The latch on disk, once one is there while ``joints`` is not latched and ``held()`` is
    false (this program's own latch, or a release under way). Read in a thread every
    LATCH_POLL_S: another program's lock never holds up the loop. A read during which this
    link latched is not used: it may be this program's own e-stop's write, released since."""
    while True:
        await asyncio.sleep(LATCH_POLL_S)
        if joints.estopped or held():
            continue
        seen = joints.latches
        try:
            latch = await asyncio.to_thread(store.estop_latch_held)
        except (OSError, sqlite3.Error):  # locked, or a bad disk: the next poll tries again
            continue
        if latch is not None and joints.latches == seen and not joints.estopped and not held():
            return latch


def this_program(what: str) -> str:
    """How the database names this program to the one that latched: "the service (pid 12 on
    lab-pc)"."""
    return f"{what} (pid {os.getpid()} on {socket.gethostname()})"


async def tell_taken(store: RunStore, latch: dict[str, str], program: str, reached: bool) -> None:
    """Say in the database that ``program`` stopped its hand for ``latch`` (logged if the disk
    does not take it: the stop stands either way)."""
    try:
        await asyncio.to_thread(store.took_estop, latch["since"], program, reached)
    except (OSError, sqlite3.Error) as e:
        log.warning("the hand was stopped for the latch on disk, but the database did not take "
                    "the note saying so: %s", e)  # fmt: skip
