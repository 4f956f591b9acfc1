"""Files written whole or not at all (the CLI's and the client's exports)."""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def whole_file(path: str | Path, binary: bool) -> Iterator[IO[Any]]:
    """``path`` written whole or not at all: into a new file beside it, which takes its place
    once complete. An export interrupted (Ctrl-C, SIGTERM, a full disk, a lost connection) left
    a truncated file that no reader opens, in place of any earlier one. A device or a pipe
    (``-o /dev/stdout``) is written directly: it is no file to replace."""
    target = Path(path)
    mode, newline = ("wb", None) if binary else ("w", "")
    if target.exists() and not target.is_file():
        with open(target, mode, newline=newline) as direct:
            yield direct
        return
    tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.part")
    # created as open() would create the file itself: 0o666 less the umask
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
    except OSError as e:  # named as the file asked for, not the hidden one beside it
        raise type(e)(e.errno, e.strerror, str(target)) from None
    try:
        with open(fd, mode, newline=newline) as fh:
            yield fh
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
