"""The 3-D view's server prints nothing of its own: with ``--log-format json`` every line on
the service's stderr is a JSON log record, and its stdout carries only its announcement."""

from __future__ import annotations

import logging

import pytest

from sdh2svc.service.viewer import _quietly, start_viser


class _Kept(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def test_viser_prints_nothing_on_stdout_or_stderr(
    capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # no handler left by a CLI test before on a stream since closed (the server's own loggers,
    # websockets', log through the root)
    monkeypatch.setattr(logging.getLogger(), "handlers", [])
    # a handler of its own, not the root's: a CLI test before may have left one there on a
    # stream since closed
    log = logging.getLogger("sdh2svc.service.viewer")
    kept, level, propagate = _Kept(), log.level, log.propagate
    log.addHandler(kept)
    log.setLevel(logging.DEBUG)
    log.propagate = False
    try:
        server = start_viser("127.0.0.1", 0, lambda _origin, _page: True)
        _quietly(server.stop)
    finally:
        log.removeHandler(kept)
        log.setLevel(level)
        log.propagate = propagate
    out, err = capfd.readouterr()
    assert (out, err) == ("", "")
    # what viser printed (its banner, "Server stopped") is in the log, at DEBUG
    printed = " ".join(m for m in kept.messages if m.startswith("viser printed"))
    assert "Server stopped" in printed
