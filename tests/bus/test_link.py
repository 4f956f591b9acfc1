"""Opening a line (bus.link): a device is the link's alone, a URL the links cannot watch is
refused at once, and two lines on one port are refused before either is opened."""

from __future__ import annotations

import asyncio
import errno
import os
import pty
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
