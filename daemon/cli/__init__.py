"""The ``mocapd`` command line (also ``python -m daemon``).

One module per command group registers its subcommands next to their handlers (:data:`COMMANDS`);
this module is the one place that turns what goes wrong into an exit status and one line on stderr:

* 0: done; 2: bad input (a :class:`~daemon.errors.MocapdError`: unreadable or malformed files, bad
  options), one line naming the file, line, field or option;
* 130 on SIGINT (Ctrl-C), 143 on SIGTERM: "interrupted" / "terminated"; every file being written is
  left as it was (outputs are written beside their target and renamed into place). A signal that
  comes once the command's outputs are in place (:func:`daemon.storage.placed`) is too late: the
  command finishes (a summary at most) with its own status;
* 70 on anything else: one line saying it is a bug in mocapd and how to report it; the traceback
  only with ``--debug``.

The command modules are imported inside :func:`main`, after the signal handlers are in place, so an
interrupt during start-up is handled like any other.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

COMMANDS = (
    "daemon.cli.recordings",
    "daemon.cli.search",
    "daemon.cli.learn",
    "daemon.cli.detect",
    "daemon.cli.segment",
    "daemon.cli.service",
    "daemon.cli.cluster",
    "daemon.cli.view",
)
"""The command groups, in the order ``--help`` lists them; each has ``register(subparsers)``."""

EXIT_USAGE = 2
EXIT_BUG = 70
BUG_REPORT = (
    "this is a bug in mocapd; please report it to the mocapd developers "
    "(docs/command-line.md, 'Reporting bugs') with the command line and the output of the same "
    "command with --debug"
)


class Terminated(BaseException):
    """SIGTERM arrived; like :class:`KeyboardInterrupt`, it unwinds the stack so outputs are cleaned."""


class Interrupted(KeyboardInterrupt):
    """SIGINT arrived. Not a plain :class:`KeyboardInterrupt`: when one of those leaves code run by
    ``exec`` or ``eval`` of a string (as the dataclasses and named tuples made while modules are
    imported are), CPython ends the process by SIGINT after :func:`main` returned 130, even though
    :func:`main` handled it."""


_RECEIVED: list[int] = []
"""The signals the handlers below received during this command: a signal's exception raised inside
a C extension may come back as another error with no trace of it (pybind11 reports "incompatible
function arguments" when one lands while it converts a call's arguments, as in matplotlib)."""


def _too_late() -> bool:
    """Whether the command's outputs are in place (:func:`daemon.storage.placed`; the module is
    looked up, not imported, in a signal handler: none placed anything before it was imported, nor
    while it is being imported, when it may not have the function yet)."""
    placed = getattr(sys.modules.get("daemon.storage"), "placed", None)
    return placed is not None and bool(placed())


def _terminate(signum: int, frame: FrameType | None) -> None:
    if not _too_late():
        _RECEIVED.append(signal.SIGTERM)
        raise Terminated


def _interrupt(signum: int, frame: FrameType | None) -> None:
    if not _too_late():
        _RECEIVED.append(signal.SIGINT)
        raise Interrupted


def _unraisable(hook: Callable[[Any], object]) -> Callable[[Any], object]:
    """A ``sys.unraisablehook`` for a signal whose exception landed where Python cannot raise it
    (a weak reference's or a finalizer's callback: it would print "Exception ignored" and lose the
    signal): the signal is sent again a moment later from a helper thread, so the main thread's
    handler runs once the callback and this hook are over. Anything else goes to ``hook``."""

    def again(unraisable: Any) -> object:
        for kind, signum in ((Interrupted, signal.SIGINT), (Terminated, signal.SIGTERM)):
            if isinstance(unraisable.exc_value, kind):
                later = threading.Timer(0.01, signal.raise_signal, (signum,))  # once the hook is left
                later.daemon = True
                later.start()
                return None
        return hook(unraisable)

    return again


def _signal_within(exc: BaseException) -> int | None:
    """The signal whose exception caused ``exc`` (its ``__cause__`` or ``__context__`` chain), if one
    did: Python wraps an exception raised where it calls a hook of class creation ("Error calling
    __set_name__ ...", as a signal arriving while matplotlib is imported does) in a RuntimeError."""
    seen: set[int] = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:
        seen.add(id(link))
        if isinstance(link, KeyboardInterrupt):
            return signal.SIGINT
        if isinstance(link, Terminated):
            return signal.SIGTERM
        link = link.__cause__ or link.__context__
    return None


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are :class:`~daemon.errors.UsageError` (one line, exit 2)."""

    def error(self, message: str) -> NoReturn:
        from daemon.errors import UsageError

        raise UsageError(f"{message} (see {self.prog} --help)")


def package_version() -> str:
    try:
        return version("mocapd")
    except PackageNotFoundError:
        return "unknown (not installed)"


def parser() -> Parser:
    """The whole command line, every command group registered."""
    top = Parser(prog="mocapd", description="Streaming motion recognition over ASF/AMC motion capture.")
    top.add_argument("--version", action="version", version=f"mocapd {package_version()}")
    top.add_argument(
        "--config", type=Path, default=None, help="config.yaml to read (default: built-in defaults)"
    )
    top.add_argument("--debug", action="store_true", help="print the traceback of an internal error")
    sub = top.add_subparsers(required=True, metavar="COMMAND", parser_class=Parser)
    for name in COMMANDS:
        importlib.import_module(name).register(sub)
    return top


def _say(message: str) -> None:
    from daemon.errors import printable

    with contextlib.suppress(OSError):  # stderr closed: there is no one left to tell
        print(f"mocapd: {printable(message)}", file=sys.stderr, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``); returns the exit status. Run as the
    program (no ``argv``), it returns with SIGINT and SIGTERM ignored: the command is over, and one
    arriving while the interpreter shuts down (a tenth of a second or more) must not end a finished
    command by that signal instead of its status."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in arguments
    _RECEIVED.clear()
    if (forget := getattr(sys.modules.get("daemon.storage"), "forget_placed", None)) is not None:
        forget()  # an earlier command of this process placed its outputs
    previous: dict[signal.Signals, Any] = {}
    try:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not ignored (``command &``)
            previous[signal.SIGINT] = signal.signal(signal.SIGINT, _interrupt)
        previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, _terminate)
        sys.unraisablehook = _unraisable(sys.__unraisablehook__)
        from daemon.config import load_config
        from daemon.errors import FileAccessError, MocapdError

        try:
            args = parser().parse_args(arguments)
            debug = args.debug
            status: int = args.func(args, load_config(args.config, os.environ))
            sys.stdout.flush()
            return status
        except MocapdError as exc:
            if _RECEIVED:  # the error may be the signal's doing; the user asked to stop anyway
                raise
            _say(str(exc))
            return EXIT_USAGE
        except BrokenPipeError:
            # The reader of our stdout went away (``| head``): nothing is wrong, nothing more to say.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 0
        except OSError as exc:
            _say(str(FileAccessError.from_os_error(exc)))
            return EXIT_USAGE
    except KeyboardInterrupt:
        _say("interrupted")
        return 128 + signal.SIGINT
    except Terminated:
        _say("terminated")
        return 128 + signal.SIGTERM
    except Exception as exc:
        stopped = _signal_within(exc) or (_RECEIVED[-1] if _RECEIVED else None)
        if stopped is not None:  # a signal that Python or an extension turned into another error
            _say("interrupted" if stopped == signal.SIGINT else "terminated")
            return 128 + stopped
        if debug:
            traceback.print_exc()
        _say(f"internal error: {type(exc).__name__}: {exc} ({BUG_REPORT})".replace("\n", " "))
        return EXIT_BUG
    finally:
        for number, handler in previous.items():
            signal.signal(number, signal.SIG_IGN if argv is None else handler)
        sys.unraisablehook = sys.__unraisablehook__
