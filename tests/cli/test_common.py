"""CLI helpers: the progress rule (``--verbose``, else only when stderr is a terminal)."""

from __future__ import annotations

import sys

from lungdeform.cli import common


def test_progress_enabled_follows_verbose_then_terminal(monkeypatch, capsys):
    # under pytest stderr is captured, not a terminal: progress is off unless --verbose set it on
    monkeypatch.setitem(common.VERBOSE, "on", None)
    assert not sys.stderr.isatty() and common.progress_enabled() is False
    common.say("hidden")
    assert capsys.readouterr().err == ""
    monkeypatch.setitem(common.VERBOSE, "on", True)
    assert common.progress_enabled() is True  # --verbose: shown even when not a terminal
    common.say("shown")
    assert capsys.readouterr().err == "shown\n"
    monkeypatch.setitem(common.VERBOSE, "on", None)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert common.progress_enabled() is True  # no --verbose, but a terminal: progress shown


def test_version_prints_without_a_command(capsys):
    # --version is eager: it prints the package version and exits 0 before any command is needed
    from lungdeform import __version__
    from lungdeform.cli.main import main

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == __version__
