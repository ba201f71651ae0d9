"""``hdhil --version``: one line ``hdhil <version>`` from the installed distribution, exit 0."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import PackageNotFoundError
from pathlib import Path

import pytest

from hdhil import cli
from hdhil.cli import main


def test_version_prints_the_distribution_version_and_exits_0(capsys):
    from importlib.metadata import version

    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"hdhil {version('hdhil')}\n"


def test_version_is_unknown_when_hdhil_is_not_installed(monkeypatch):
    def not_installed(name: str) -> str:
        raise PackageNotFoundError(name)

    monkeypatch.setattr("importlib.metadata.version", not_installed)
    assert cli.version() == "unknown"


_SCRIPT = Path(sys.executable).with_name("hdhil")


@pytest.mark.parametrize("command", [[str(_SCRIPT)], [sys.executable, "-m", "hdhil"]])
def test_version_from_the_console_script(command):
    from importlib.metadata import version

    if not Path(command[0]).is_file():
        pytest.skip("no hdhil console script beside this interpreter")
    done = subprocess.run([*command, "--version"], capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stdout, done.stderr) == (0, f"hdhil {version('hdhil')}\n", "")
