"""CLI helpers: the progress rule (``--verbose``, else only when stderr is a terminal), library
parameters said as options, and the rule that a command's module imports no other command's."""

from __future__ import annotations

import ast
import inspect
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import pytest
import typer
from typer.testing import CliRunner

from lungdeform.cli import common
from lungdeform.errors import InputError, ReadError


def _command_context(verbose: bool | None) -> typer.Context:
    """The context a command runs in: a root whose object is what ``lungdeform [--verbose]`` made
    (None: no root callback ran, as for library code called outside the CLI)."""
    command = typer.main.get_command(typer.Typer(callback=lambda: None))
    root = typer.Context(command, obj=None if verbose is None else common.Verbosity(verbose))
    return typer.Context(command, parent=root)


def test_progress_enabled_follows_verbose_then_terminal(monkeypatch, capsys):
    # under pytest stderr is captured, not a terminal: progress is off unless --verbose set it on
    assert not sys.stderr.isatty()
    for verbose in (None, False):
        with _command_context(verbose):
            assert common.progress_enabled() is False
            common.say("hidden")
    assert common.progress_enabled() is False  # outside any command
    assert capsys.readouterr().err == ""
    with _command_context(True):
        assert common.progress_enabled() is True  # --verbose: shown even when not a terminal
        common.say("shown")
    assert capsys.readouterr().err == "shown\n"
    assert common.progress_enabled() is False  # the setting lived in that command's context only
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    with _command_context(False):
        assert common.progress_enabled() is True  # no --verbose, but a terminal: progress shown


def test_verbose_reaches_the_command_through_its_context(monkeypatch, capsys):
    # end to end: `lungdeform --verbose CMD` shows CMD's progress on a captured (non-terminal)
    # stderr, and the same command without --verbose shows none; nothing outlives the call
    from lungdeform.cli.main import make_app

    seen = []
    app = make_app()

    @app.command("probe-verbosity")
    def _probe():
        seen.append(common.progress_enabled())

    for argv in (["--verbose", "probe-verbosity"], ["probe-verbosity"]):
        with pytest.raises(SystemExit) as done:
            app(argv)
        assert done.value.code == 0
    assert seen == [True, False]
    assert common.progress_enabled() is False


def test_version_prints_without_a_command(capsys):
    # --version is eager: it prints the package version and exits 0 before any command is needed
    from lungdeform import __version__
    from lungdeform.cli.main import main

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == __version__


def test_option_names_says_the_option_a_library_error_names():
    # a library error that begins with a parameter's name is said with the command's option; other
    # errors, and names that only begin with a known one (side_check), pass unchanged
    options = {"folds": "--folds", "max_evaluations": "--evaluations", "side": "--side"}
    with pytest.raises(InputError, match=r"^--folds must be between 2 and the number of landmarks \(12\), got 20$"):
        with common.option_names(options):
            raise InputError("folds must be between 2 and the number of landmarks (12), got 20")
    with pytest.raises(InputError, match="^--evaluations must be a whole number >= 1, got 0$"):
        with common.option_names(options):
            raise InputError("max_evaluations must be a whole number >= 1, got 0")
    for text in ("side_check must be True or False, got 'no'", "ee.ply: folds of the lung"):
        with pytest.raises(InputError, match=f"^{text}$"):
            with common.option_names(options):
                raise InputError(text)
    with pytest.raises(ReadError, match="^folds.txt: missing$"):  # not an InputError: untouched
        with common.option_names(options):
            raise ReadError("folds.txt: missing")


def test_no_command_module_imports_another():
    # a command's module parses, calls the library and picks exit codes: what two commands share
    # lives in the library or in cli/common, never in another command's module
    cli = Path(common.__file__).parent
    shared = {"common", "main", "__init__"}
    known = set()
    commands = {p.stem for p in cli.glob("*.py")} - shared
    for path in cli.glob("*.py"):
        if path.stem in shared:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] if node.level == 0 else [node.module or a.name for a in node.names]
                for name in names:
                    leaf = name.removeprefix("lungdeform.cli.") if node.level == 0 else name
                    if (path.stem, leaf) in known:
                        continue
                    assert not (leaf in commands and (node.level or name.startswith("lungdeform.cli."))), \
                        f"{path.name} imports the command module {name}"


def _float_options():
    """(command words, option name, callback) of every float option of the CLI, from the typer apps
    (cli/track.py excepted: its options are checked by its own module)."""
    import typer

    from lungdeform.cli.main import make_app

    found = []

    def walk(app, words):
        for cmd in app.registered_commands:
            name = cmd.name or cmd.callback.__name__.replace("_", "-")
            for p in inspect.signature(cmd.callback).parameters.values():
                # an option declared as a default (``x: float = typer.Option(...)``) or, in the option
                # dataclasses of common.takes, as ``Annotated[float, typer.Option(...)]``
                meta = getattr(p.annotation, "__metadata__", ())
                info = next((m for m in meta if isinstance(m, typer.models.OptionInfo)), p.default)
                if isinstance(info, typer.models.OptionInfo) and "float" in str(p.annotation):
                    # Annotated: typer reads the first positional of typer.Option (its default) as a name
                    decls = (*info.param_decls, *([info.default] if isinstance(info.default, str) else []))
                    opt = max(decls, key=len)
                    found.append(((*words, name), opt, info.callback))
        for group in app.registered_groups:
            walk(group.typer_instance, (*words, group.name))

    walk(make_app(), ())
    return [f for f in found if f[0] != ("track",)]


FLOAT_OPTIONS = _float_options()


def test_every_float_option_has_a_range_check():
    # why: a float option without a range check takes nan, inf or 1e308 silently (stream printed nan
    # volumes for --v-ee-ml nan; dvf --node-mm 1e9 wrote a zero field); each carries a callback of
    # common.bounded (or one with its .bounds), run as the command line is parsed
    assert len(FLOAT_OPTIONS) >= 25
    missing = [(" ".join(c), o) for c, o, cb in FLOAT_OPTIONS if not hasattr(cb, "bounds")]
    assert not missing, missing


@pytest.mark.parametrize("value", ["nan", "inf", "-1e308", "1e308"])
@pytest.mark.parametrize("words, option", [(c, o) for c, o, _ in FLOAT_OPTIONS],
                         ids=[f"{' '.join(c)} {o}" for c, o, _ in FLOAT_OPTIONS])
def test_a_non_finite_or_absurd_number_exits_2_naming_the_option(words, option, value, tmp_path, capsys):
    # why: each float option refuses a non-finite or out-of-range value before any work, with one
    # line naming the option and its range; the option comes first on the command line, so it is
    # checked before the missing arguments are
    from lungdeform.cli.main import main

    assert main([*words, option, value]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {option} must be"), err
    assert not list(tmp_path.iterdir())


@dataclass(frozen=True, kw_only=True)
class _Border:
    border_mm: Annotated[float, typer.Option("--border-mm", callback=common.bounded(0, 100, "mm"), help="B.")] = 10.0
    name: Annotated[str | None, typer.Option("--name", help="N.")] = None


@dataclass(frozen=True, kw_only=True)
class _Options:
    model: Annotated[Path, typer.Argument(help="M.")]
    scale: Annotated[float | None, typer.Option("--scale", help="S.")] = None
    out: Annotated[Path, typer.Option("--out", help="O.")]  # required, after a defaulted field
    flag: Annotated[bool, typer.Option("--flag/--no-flag", help="F.")] = True
    border: _Border = _Border()


def _takes_app():
    app = typer.Typer()

    @app.callback()
    def root(ctx: typer.Context, verbose: bool = typer.Option(False, "--verbose")) -> None:
        ctx.obj = common.Verbosity(verbose)

    @app.command("go")
    @common.takes(_Options)
    def go(opts: _Options) -> None:
        """Go somewhere."""
        common.say("progress")
        typer.echo(repr(opts))

    return app


def test_takes_gives_typer_the_fields_of_the_options_and_the_command_one_object(monkeypatch):
    # why: the commands take one options dataclass (issue 29: no function over 8 parameters); typer
    # must still see every field as a parameter (nested groups flattened, in field order), with its
    # default or required, and the command gets the values as typed on the command line
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    app = _takes_app()
    sig = inspect.signature(app.registered_commands[0].callback)
    assert list(sig.parameters) == ["model", "scale", "out", "flag", "border_mm", "name"]
    assert sig.parameters["out"].default is inspect.Parameter.empty and sig.parameters["flag"].default is True
    runner = CliRunner()
    done = runner.invoke(app, ["--verbose", "go", "m.npz", "--out", "o", "--scale", "2.5", "--no-flag",
                               "--border-mm", "3", "--name", "GTV"])
    assert done.exit_code == 0, done.output
    assert done.output.splitlines() == ["progress", repr(_Options(model=Path("m.npz"), scale=2.5, out=Path("o"),
                                                                 flag=False, border=_Border(border_mm=3.0, name="GTV")))]
    plain = runner.invoke(app, ["go", "m.npz", "--out", "o"])
    assert plain.output.strip() == repr(_Options(model=Path("m.npz"), out=Path("o")))  # defaults; no progress
    assert runner.invoke(app, ["go", "m.npz"]).exit_code == 2  # --out required
    help_text = runner.invoke(app, ["go", "--help"]).output
    assert "Go somewhere." in help_text and all(o in help_text for o in ("--scale", "--out", "--no-flag", "--border-mm"))
    bad = runner.invoke(app, ["go", "m.npz", "--out", "o", "--border-mm", "nan"])  # the bounded callback runs
    assert isinstance(bad.exception, InputError) and str(bad.exception).startswith("--border-mm must be")


def test_takes_refuses_an_option_given_twice():
    # why: two groups declaring one field name would make typer keep only one of them silently

    @dataclass(frozen=True, kw_only=True)
    class Twice:
        name: Annotated[str | None, typer.Option("--other-name")] = None
        border: _Border = _Border()

    with pytest.raises(TypeError, match="name given twice"):
        common.takes(Twice)


def test_an_output_folder_that_takes_no_file_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    # why: `dvf --out u.mha --out-reg /proc/reg.dcm` wrote u.mha and then failed on the REG (and
    # `track --out-rtstruct` likewise left its trajectories): an output's folder is now tried with a
    # temporary file before any work, so the refusal comes first and nothing is written
    import errno
    import tempfile

    from lungdeform.cli.common import check_output
    from lungdeform.cli.main import main
    from lungdeform.io.modelfile import save_model
    from tests.browser.support import two_lungs
    real = tempfile.NamedTemporaryFile
    locked = tmp_path / "locked"
    locked.mkdir()

    def refusing(*args, dir=None, **kwargs):  # noqa: A002 - tempfile's own name
        if dir is not None and Path(dir) == locked:
            raise PermissionError(errno.EACCES, "Permission denied", str(locked))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "NamedTemporaryFile", refusing)
    with pytest.raises(InputError, match=r"--out-reg .*reg\.dcm: cannot write in .*locked \(Permission denied\)"):
        check_output(locked / "reg.dcm", option="--out-reg")
    with pytest.raises(InputError, match="cannot write in"):
        check_output(locked / "new" / "deeper" / "u.mha")  # the nearest existing folder is tried
    assert check_output(tmp_path / "fine.mha") == tmp_path / "fine.mha"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["locked"]  # the probe leaves nothing
    save_model(tmp_path / "m.npz", two_lungs(2))
    rc = main(["dvf", str(tmp_path / "m.npz"), "--reference", str(tmp_path / "m.npz"), "--volume-ml", "100",
               "--out", str(tmp_path / "u.mha"), "--out-reg", str(locked / "reg.dcm")])
    err = capsys.readouterr().err
    assert rc == 2 and "cannot write in" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "u.mha").exists()
