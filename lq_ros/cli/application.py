"""The ``lq`` command line: the typer app, one module per command (lq_ros/cli/<command>.py), and ``main``."""

from __future__ import annotations

import atexit
import os
import sys
from pathlib import Path
from typing import Annotated

import typer

from lq_ros.cli.common import console
from lq_ros.cli.demo import demo
from lq_ros.cli.eval import eval_
from lq_ros.cli.plan import plan
from lq_ros.cli.reindex import reindex
from lq_ros.cli.replay import replay
from lq_ros.cli.report import report
from lq_ros.cli.run import run
from lq_ros.cli.score import score
from lq_ros.cli.sweep import sweep
from lq_ros.core.bounded_file import FileRefused
from lq_ros.core.safe_write import WriteRefused
from lq_ros.training import cli as _learned_cli

app = typer.Typer(add_completion=False, no_args_is_help=True, help="LIBERO-LQ: latency-aware VLA evaluation on ROS 2.")
#: Width of --help when the output is no terminal (a pipe, a file): wide enough for every option name.
PIPED_WIDTH = 160


def _print_version(value: bool) -> None:
    if value:
        import lq_ros
        from lq_ros.core.run_config import git_commit

        print(f"lq {lq_ros.__version__} (commit {git_commit()})")
        raise typer.Exit()


@app.callback()
def _options(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="Print the version and commit, then exit."
        ),
    ] = False,
) -> None:
    """LIBERO-LQ: latency-aware VLA evaluation on ROS 2."""


app.command()(run)
app.command()(demo)
app.command()(score)
app.command()(sweep)
app.command(name="eval")(eval_)
app.command()(report)
app.command()(plan)
app.command()(replay)
app.command()(reindex)
# Learned policies: demonstrations and training (lq_ros/training/cli.py).
app.command()(_learned_cli.collect)
app.command()(_learned_cli.train)


def main() -> int:
    """``lq``: a usage mistake is one line on stderr and exit code 2 (no usage panel, no traceback)."""
    try:
        from typer._click import exceptions  # typer vendors click (0.2x)
    except ImportError:  # pragma: no cover - an older typer on click
        from click import exceptions

    try:
        from lq_ros.transport.processes import executor_choice, node_forks_choice, sim_cpu_choice

        executor_choice(dict(os.environ))  # the node processes' executor: refused before anything starts
        sim_cpu_choice(dict(os.environ))  # whether the stack pins its sim to a CPU
        node_forks_choice(dict(os.environ))  # whether the stack forks its nodes from a process that imported them
        from lq_ros.sim import model_cache

        model_cache.settings(os.environ)  # the compiled-model cache's variables
    except ValueError as exc:
        console.print(f"[red]error:[/red] {exc}", soft_wrap=True, highlight=False)
        return 2
    _importable_current_directory()
    if not sys.stdout.isatty() and "TERMINAL_WIDTH" not in os.environ and may_print_help(sys.argv[1:]):
        # (with rich's markdown renderer: imported only for help, not for every command). Not ``import
        # typer.rich_utils``, which would make ``typer`` a local name of main() for the whole function.
        from typer import rich_utils

        rich_utils.MAX_WIDTH = PIPED_WIDTH  # --help piped: no option name cut short
    from lq_ros.run.quiet import quiet_simulator_banners

    quiet_simulator_banners()
    try:
        return app(standalone_mode=False) or 0
    except exceptions.NoArgsIsHelpError as exc:
        exc.show()
        return exc.exit_code
    except exceptions.UsageError as exc:
        from rich.markup import escape

        where = exc.ctx.command_path if exc.ctx is not None else "lq"
        message = _choice_hint(" ".join(exc.format_message().split()))
        console.print(f"[red]error:[/red] {escape(f'{where}: {message} (see {where} --help)')}", soft_wrap=True,
                      highlight=False)  # fmt: skip
        return exc.exit_code
    except exceptions.ClickException as exc:
        exc.show()
        return exc.exit_code
    except typer.Abort:
        console.print("Aborted!")
        return 1
    except (WriteRefused, FileRefused) as exc:  # a file or folder the stack will not write or read: one line
        from rich.markup import escape

        console.print(f"[red]error:[/red] {escape(' '.join(str(exc).split()))}", soft_wrap=True, highlight=False)
        return 2
    except Exception as exc:  # noqa: BLE001 - a bug: one line and where its traceback is, never a traceback
        return _unexpected(exc)


def _unexpected(exc: Exception) -> int:
    """An exception nobody expected (a bug): one line on stderr naming it and the file holding its traceback (in
    this user's private temporary folder); exit code 1."""
    import tempfile
    import time
    import traceback

    from rich.markup import escape

    from lq_ros.core.safe_write import write_text
    from lq_ros.transport.processes import private_folder

    what = " ".join(f"{type(exc).__name__}: {exc}".split())[:300]
    try:
        folder = private_folder(Path(tempfile.gettempdir()) / f"lq_ros_errors-{os.getuid()}")
        log = folder / f"lq-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.log"
        write_text(log, f"lq {' '.join(sys.argv[1:])}\n" + "".join(traceback.format_exception(exc)))
        where = f"the traceback: {log}"
    except Exception as failed:  # noqa: BLE001 - the message must still reach the user
        where = f"no traceback file ({type(failed).__name__}: {failed})"
    console.print(f"[red]error:[/red] unexpected {escape(what)} (a bug in lq; {escape(where)})", soft_wrap=True,
                  highlight=False)  # fmt: skip
    return 1


def may_print_help(args: list[str]) -> bool:
    """Whether ``lq ARGS`` may print a help text: ``--help`` anywhere, or no command (``lq`` alone shows it)."""
    return not args or "--help" in args


def _importable_current_directory() -> None:
    """``--policy module:Class`` finds a module in the current directory, as ``python -m`` would (after installed
    packages, so a file there never hides one lq itself uses); PYTHONSAFEPATH / ``python -P`` turn it off."""
    if not sys.flags.safe_path and os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.append(os.getcwd())


def _choice_hint(message: str) -> str:
    """Click's message for a value outside an option's choices, plainer and with the closest choice:
    "Invalid value for '--mode': 'asynch' is not one of 'sync', 'async'. (did you mean 'async'?)"."""
    import re

    from lq_ros.run.validation import did_you_mean

    message = message.replace("Value error, ", "")
    found = re.search(r"'([^']*)' is not one of ((?:'[^']*'(?:, )?)+)", message)
    if found:
        message += did_you_mean(found.group(1), re.findall(r"'([^']*)'", found.group(2)))
    return message


def entry() -> None:
    """The ``lq`` command: :func:`main`, then leave without tearing the interpreter down when nothing needs it.

    Once every file is closed and everything printed, tearing down the modules of an in-process run (MuJoCo,
    robosuite, numba and the rest) takes 0.1-0.2 s. The exit handlers still run; the teardown is skipped only
    when ROS was never loaded in this process (DDS removes its shared-memory files in its destructors) and no
    non-daemon thread is still running.
    """
    import threading

    code = main()
    run_exit_handlers = getattr(atexit, "_run_exitfuncs", None)
    others = [t for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon]
    if "rclpy" in sys.modules or others or run_exit_handlers is None:
        sys.exit(code)
    run_exit_handlers()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
