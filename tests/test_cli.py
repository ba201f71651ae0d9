"""The ``hdhil`` command line: the lazy command table and what start-up imports.

``cli.COMMANDS`` lists every subcommand with its one-line help so that ``hdhil --help``
need not import the command modules; these tests keep that table equal to what each
module registers, and check that asking for help or starting a run does not load the
heavy libraries only other commands (or later stages) need.  Times are measured by
``hdhil bench`` (start-up section), never here.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from hdhil.cli import COMMANDS, build_parser


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, str | None]:
    """Name -> help of every subcommand the parser lists."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {action.dest: action.help for action in sub._choices_actions}


def test_the_command_table_equals_what_the_modules_register():
    registered = _subcommands(build_parser(["--help"], load_all=True))
    assert registered == {name: help_text for name, (_, help_text) in COMMANDS.items()}


def test_each_module_registers_the_commands_the_table_gives_it():
    """Loading one module (as running one of its commands does) registers its own
    commands with their full parsers, and only those."""
    for name, (module, _) in COMMANDS.items():
        parser = build_parser([name])
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        full = {n for n, p in sub.choices.items() if p.add_help}
        assert full == {n for n, (m, _) in COMMANDS.items() if m == module}, name


def _modules_after(code: str) -> list[str]:
    """Top-level packages of interest loaded by ``code`` in a fresh interpreter."""
    heavy = ("scipy", "matplotlib", "numpy", "cantools", "canopen", "pandas")
    probe = (
        f"import sys\n{code}\n"
        f"import json; print(json.dumps(sorted({{m for m in sys.modules if m in {heavy!r}}})))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=120, check=True).stdout  # fmt: skip
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("argv", [["--help"], ["dump", "--help"]])
def test_help_loads_no_heavy_library(argv):
    """Nothing heavy beyond what ``import can`` itself loads here (python-can imports
    asammdf, and with it numpy and pandas, where the mf4 extra is installed): the goal
    is set against python-can's own start-up."""
    code = f"from hdhil.cli import main\ntry:\n    main({argv!r})\nexcept SystemExit:\n    pass"
    baseline = set(_modules_after("import can"))
    assert set(_modules_after(code)) - baseline == set()


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_run_starts_without_scipy_signal_stats_or_matplotlib():
    """``hdhil run``'s modules import numpy, cantools and canopen, which the first cycle
    needs, but not scipy.signal/scipy.stats nor matplotlib, and neither do the
    evaluation's baselines, which every run scores; the plant's first step needs no
    scipy module either (:mod:`hdhil.core.expm`)."""
    code = (
        "import hdhil.commands.run, hdhil.rig.runner, hdhil.firmware.baselines\n"
        "print([m for m in ('scipy.signal', 'scipy.stats', 'scipy.linalg', 'matplotlib') "
        "if m in sys.modules])"
    )
    probe = f"import sys\n{code}"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=120, check=True).stdout  # fmt: skip
    assert out.strip() == "[]"


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_free_motion_run_imports_no_scipy(tmp_path):
    """A whole free-motion run without evaluation imports no scipy module: the plant's
    exact discretisation calls scipy's compiled expm kernel without scipy.linalg, whose
    import (it clones the numpy namespace: numpy.f2py, numpy.ma, ...) was the largest
    part of the start-up.  Where this scipy's expm wrapper is not the one
    :mod:`hdhil.core.expm` repeats, scipy.linalg does the work and nothing else."""
    from hdhil.core.expm import scipy_kernel

    code = (
        "import sys\n"
        "from hdhil.cli import main\n"
        "code = main(['run', '--scenario', 'free-motion', '--duration', '0.002', '--seed', '5',"
        " '--no-evaluate', '--trace', '', '--quiet'])\n"
        "print(code, sorted({m.split('.')[0] + '.' + m.split('.')[1] for m in sys.modules"
        " if m.startswith('scipy.')} | {m for m in ('scipy', 'numpy.f2py', 'numpy.ma')"
        " if m in sys.modules}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True, cwd=tmp_path).stdout  # fmt: skip
    exit_code, loaded = out.strip().splitlines()[-1].split(" ", 1)
    assert exit_code == "0"
    if scipy_kernel() is None:
        assert "scipy.linalg" in loaded
    else:
        assert loaded == "[]"


def test_an_import_error_caused_by_ctrl_c_is_an_interruption(monkeypatch, capsys) -> None:
    """A Ctrl-C inside a compiled extension's import surfaces as the ImportError the
    extension raises, with the KeyboardInterrupt as its context: one line, exit 130."""
    from hdhil import cli

    def interrupted_import(_args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ImportError("initialization of an extension failed") from None

    def failed_import(_args):
        raise ImportError("no module named nothing")

    class Parser:
        func = None

        def parse_args(self, argv):
            return argparse.Namespace(func=self.func)

    parser = Parser()
    monkeypatch.setattr(cli, "build_parser", lambda argv: parser)
    parser.func = interrupted_import
    assert cli.main(["x"]) == 130
    assert capsys.readouterr().err == "hdhil: interrupted\n"
    parser.func = failed_import
    with pytest.raises(ImportError, match="no module named nothing"):
        cli.main(["x"])


def test_every_interruption_ends_with_the_line(monkeypatch, capsys) -> None:
    """A command that stopped cleanly at a signal returns 130 and main says so (run, soak,
    log, emulate and firmware printed their summary only); an error of any kind raised
    because of a Ctrl-C is an interruption too, any other keeps its traceback."""
    from hdhil import cli

    def stopped(_args):
        print("summary")
        return 130

    def interrupted(_args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise RuntimeError("a library's own error while Ctrl-C was handled") from None

    class Parser:
        func = None

        def parse_args(self, argv):
            return argparse.Namespace(func=self.func, command="run")

    parser = Parser()
    monkeypatch.setattr(cli, "build_parser", lambda argv: parser)
    for func in (stopped, interrupted):
        parser.func = func
        assert cli.main(["run"]) == 130
        assert capsys.readouterr().err == "hdhil: interrupted\n"
