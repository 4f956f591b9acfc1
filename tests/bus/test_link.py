"""Opening a line (bus.link): a device is the link's alone, a URL the links cannot watch is
refused at once, and two lines on one port are refused before either is opened."""

from __future__ import annotations

import asyncio
import errno
import os
import pty
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from sdh2svc.bus.link import close_streams, open_streams
from sdh2svc.bus.tactile import TactileBus, TactileError, TactileOptions
from sdh2svc.config import ConfigError, load_config
from sdh2svc.connect import open_links


@pytest.fixture
def tty() -> Iterator[str]:
    """A pty's device path (its far end held open here)."""
    master, slave = pty.openpty()
    try:
        yield os.ttyname(slave)
    finally:
        os.close(slave)
        os.close(master)


def test_a_device_another_program_holds_is_refused_as_in_use(tty: str) -> None:
    """A second program (a second sdh2svc, SDHLibrary, a terminal) opened a line a service
    owned and wrote into it, failing only by luck, with a checksum error for a message."""

    async def main() -> str:
        _, writer = await open_streams(tty)
        try:
            with pytest.raises(serial.SerialException) as refused:
                await open_streams(tty)
        finally:
            await close_streams(writer)
        _, again = await open_streams(tty)  # closed: free again
        await close_streams(again)
        return str(refused.value)

    assert asyncio.run(main()).endswith(f"{tty} is in use by another program (it holds the "
                                        "port's lock)")  # fmt: skip


def test_a_url_without_a_file_descriptor_is_refused_at_once() -> None:
    """loop:// opened, failed at its first write and hung for ever as it closed."""

    async def main() -> str:
        with pytest.raises(serial.SerialException) as refused:
            await asyncio.wait_for(open_streams("loop://"), 10)
        return str(refused.value)

    assert "loop://: this kind of port has no file descriptor" in asyncio.run(main())


def test_both_lines_on_one_port_are_refused_before_either_is_opened(
    tty: str, tmp_path: Path
) -> None:
    """--dsa X --sdh X wrote the tactile controller's packets into the joint line for 15 s; a
    symlink to the device is the device."""
    link = str(tmp_path / "ttyUSB0")
    os.symlink(tty, link)
    cfg = load_config(use_env=False)
    with pytest.raises(ConfigError, match=f"both {link!r}: each controller has a line"):
        asyncio.run(open_links(cfg, tty, link))


@pytest.mark.parametrize("url", ["/dev/does-not-exist-dsa", "foo://x"])
def test_a_tactile_line_that_cannot_be_opened_is_named(url: str) -> None:
    """Its failure did not say which line it was; an unknown URL scheme was "a bug" (exit 70),
    where the joint line's was a line that cannot be reached."""

    async def main() -> str:
        with pytest.raises(TactileError) as refused:
            await TactileBus.open(url, TactileOptions(reconnect=False))
        return str(refused.value)

    assert asyncio.run(main()).startswith(f"tactile line {url}: cannot open: ")


def test_a_device_without_permission_says_what_to_do(monkeypatch: pytest.MonkeyPatch) -> None:
    """The usual cause in a lab is a user not in the device's group (as root, chmod cannot
    stage it: pyserial's refusal is staged instead)."""

    def refuse(url: str, **_: object) -> None:
        raise serial.SerialException(errno.EACCES, f"could not open port {url}: Permission denied")

    monkeypatch.setattr(serial, "serial_for_url", refuse)

    async def main() -> str:
        with pytest.raises(serial.SerialException) as refused:
            await open_streams("/dev/ttyUSB0")
        return str(refused.value)

    assert "no permission to open /dev/ttyUSB0: add this user to the group that owns it " \
           "(usually dialout" in asyncio.run(main())  # fmt: skip


def _open_as_nobody(path: str) -> int:
    """errno of a plain open() of ``path`` by another user (0: it opened)."""
    probe = (
        "import os, sys\n"
        "try:\n    os.close(os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY))\n"
        "except OSError as e:\n    sys.exit(e.errno)\n"
    )
    python = shutil.which("python3", path="/usr/bin:/bin") or sys.executable  # (not in our venv)
    r = subprocess.run([python, "-c", probe, path], user=65534, timeout=30)
    return r.returncode


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root, to run a probe as another user")
def test_a_plain_open_by_another_program_is_refused_while_the_line_is_ours(tty: str) -> None:
    """pyserial's lock is advisory: SDHLibrary, a terminal or `echo > /dev/ttyUSB0` opened a
    line the service held and could write into it (root is let in by the kernel whatever)."""
    os.chmod(tty, 0o666)

    async def main() -> tuple[int, int]:
        _, writer = await open_streams(tty)
        try:
            held = _open_as_nobody(tty)
        finally:
            await close_streams(writer)
        return held, _open_as_nobody(tty)

    assert asyncio.run(main()) == (errno.EBUSY, 0)


@pytest.mark.parametrize("url", ["loop://", "rfc2217://lab:2217", "foo://x"])
def test_a_url_no_line_can_be_is_refused_before_anything_opens(url: str) -> None:
    """A service that waits for its hand retried such a typo every 5 s for ever, looking up."""
    cfg = load_config(use_env=False)
    with pytest.raises(ConfigError, match="a line is a device path or one of socket://"):
        asyncio.run(open_links(cfg, url, "/dev/ttyUSB0", patient=True))


def test_two_sockets_whose_names_differ_in_case_are_two_lines() -> None:
    from sdh2svc.connect import _port

    assert _port("unix:///tmp/A.sock") != _port("UNIX:///tmp/a.sock")
    assert _port("SOCKET://lab:23") == _port("socket://lab:23")
