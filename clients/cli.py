"""`rvs`, the operator's command-line client of the RVS server.

    rvs [--host H] [--port P] [--zmq ENDPOINT] [--token-file F] [--timeout S] COMMAND ...

    rvs send LINE...                       each argument is one command line; every reply line is
                                           printed as it arrives; exit 0 only if all were OK
    rvs shell                              interactive (history in ~/.rvs_history); replies, progress
                                           and events are printed as they arrive, so `break` can be
                                           typed while a job runs. With stdin not a terminal, the
                                           lines are run one after the other.
    rvs mission run FILE [--set N=V ...]   run a mission file (see clients/mission.py)
    rvs mission check FILE [--set N=V ...] validate it with `check`; nothing moves
    rvs campaign FILE [--workers N | --scheduler ADDRESS] [--out DIR]
                                           run a campaign on Dask, each run on its own server
                                           (see clients/campaign.py); rerunning resumes it
    rvs remap PRODUCT... --workflow FILE [--workers N | --scheduler ADDRESS] [--out DATA_DIR]
                                           re-run a mapping workflow on the views dem-* products
                                           stored, on Dask, with no device (see clients/remap.py)

The text transport at 127.0.0.1:7400 is the default; `--zmq tcp://HOST:PORT` uses ZeroMQ instead
(no events there). `--token-file` sends `auth TOKEN` before anything else.
Exit status: 0 all OK; 1 a command failed; 2 nothing could be run (usage, file, connection, auth).
"""
from __future__ import annotations

import argparse
import os
import stat
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rvs_server.protocol import is_ignored

from . import campaign, mission, remap
from .gnc import DEFAULT_HOST, DEFAULT_PORT, Event, RvsClient, RvsClientError, RvsRequestError, ZmqClient

EXIT_OK, EXIT_FAILED, EXIT_NOT_STARTED = 0, 1, 2
CLI_TIMEOUT = 600.0  # seconds of silence tolerated per command; PROGRESS restarts the count
HISTORY_FILE = "~/.rvs_history"


class Printer:
    """Whole lines to stdout, one at a time: replies and events come from several threads.

    While the interactive shell waits at its prompt (`prompt` set), a line that arrives is
    written over the prompt, and the prompt and what was typed so far are drawn again below it.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.prompt: str | None = None
        self.typed: Callable[[], str] = lambda: ""

    def __call__(self, line: str) -> None:
        with self._lock:
            if self.prompt is None:
                sys.stdout.write(line + "\n")
            else:
                sys.stdout.write(f"\r\x1b[K{line}\n{self.prompt}{self.typed()}")
            sys.stdout.flush()

    def event(self, event: Event) -> None:
        self(event.line)


def warn(message: str) -> None:
    print(f"rvs: {message}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# Connecting


class StartError(Exception):
    """The command cannot start: no connection, no token, refused auth."""


def read_token(path: str) -> str:
    try:
        info = os.stat(path)
        token = Path(path).read_text().strip()
    except OSError as exc:
        raise StartError(f"token file {path}: {exc.strerror}") from None
    if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        warn(f"token file {path} is readable by others; chmod 600 {path}")
    if not token:
        raise StartError(f"token file {path} is empty")
    return token


def connect(args: argparse.Namespace, printer: Printer) -> RvsClient | ZmqClient:
    """A client as the options say, authenticated when a token file is given."""
    token = read_token(args.token_file) if args.token_file else None
    try:
        if args.zmq:
            return ZmqClient(args.zmq, timeout=args.timeout, token=token)
        return RvsClient(args.host, args.port, timeout=args.timeout, on_event=printer.event, token=token)
    except RvsRequestError as exc:
        raise StartError(f"auth refused: {exc.line}") from None
    except RvsClientError as exc:
        raise StartError(str(exc)) from None


def play(client: RvsClient | ZmqClient, line: str, printer: Printer) -> bool:
    """Send one line, print each reply line as it arrives; True when it ended OK."""
    try:
        for item in client.stream(line):
            printer(item.line)
    except RvsRequestError as error:
        printer(error.line)
        return False
    except ValueError as exc:  # a line with a line break in it
        warn(str(exc))
        return False
    return True


# ---------------------------------------------------------------------------------------------
# Commands


def command_send(args: argparse.Namespace, printer: Printer) -> int:
    all_ok = True
    with connect(args, printer) as client:
        for line in args.lines:
            if is_ignored(line):
                continue  # the server would not answer it; waiting would hang
            all_ok = play(client, line, printer) and all_ok
    return EXIT_OK if all_ok else EXIT_FAILED


def command_shell(args: argparse.Namespace, printer: Printer) -> int:
    interactive = sys.stdin.isatty()
    with connect(args, printer) as client:
        if interactive:
            greeting = client.server_version
            where = args.zmq or f"{args.host}:{args.port}"
            printer(f"connected to RVS {greeting} at {where}; Ctrl-D leaves, `quit` stops the server")
            return _interactive_shell(client, printer)
        return _scripted_shell(client, printer)


def _scripted_shell(client: RvsClient | ZmqClient, printer: Printer) -> int:
    """Lines from a pipe or file: one after the other, each waiting for its final reply."""
    all_ok = True
    for line in sys.stdin:
        if is_ignored(line):
            continue
        all_ok = play(client, line.rstrip("\r\n"), printer) and all_ok
        if client.closed:
            break
    return EXIT_OK if all_ok else EXIT_FAILED


def _interactive_shell(client: RvsClient | ZmqClient, printer: Printer) -> int:
    """Like telnet: a command runs in the background, so `status` or `break` can follow at once."""
    history = _start_history(printer)
    outcomes: list[bool] = []
    running: list[threading.Thread] = []

    def run(line: str) -> None:
        outcomes.append(play(client, line, printer))

    try:
        while not client.closed:
            try:
                line = _prompt(printer, "rvs> ")
            except EOFError:
                break
            except KeyboardInterrupt:  # like a shell: drop the line being typed
                print()
                continue
            if is_ignored(line):
                continue
            worker = threading.Thread(target=run, args=(line,), daemon=True)
            worker.start()
            running.append(worker)
            worker.join(0.2)  # quick replies print before the next prompt
        _wait_for(running)
    finally:
        _save_history(history)
    if client.closed:
        printer("the server closed the connection")
    return EXIT_OK if all(outcomes) else EXIT_FAILED


def _prompt(printer: Printer, prompt: str) -> str:
    printer.prompt = prompt
    try:
        return input(prompt)
    finally:
        printer.prompt = None


def _wait_for(threads: list[threading.Thread]) -> None:
    pending = [t for t in threads if t.is_alive()]
    if not pending:
        return
    warn(f"waiting for {len(pending)} reply(s); Ctrl-C leaves without them (jobs go on on the server)")
    try:
        for thread in pending:
            thread.join()
    except KeyboardInterrupt:
        pass


def _start_history(printer: Printer) -> Callable[[], Any] | None:
    try:
        import readline
    except ImportError:  # no readline on this platform: plain input()
        return None
    printer.typed = readline.get_line_buffer
    path = os.path.expanduser(HISTORY_FILE)
    try:
        readline.read_history_file(path)
    except OSError:
        pass
    readline.set_history_length(2000)
    return lambda: readline.write_history_file(path)


def _save_history(save: Callable[[], Any] | None) -> None:
    if save is None:
        return
    try:
        save()
    except OSError as exc:
        warn(f"history not saved: {exc}")


def command_mission(args: argparse.Namespace, printer: Printer) -> int:
    checking = args.action == "check"
    try:
        text, lines, unused = mission.load_mission(args.file, args.set or [])
    except mission.MissionError as exc:
        for problem in exc.problems:
            warn(f"{args.file}: {problem}")
        warn(f"{args.file}: nothing was sent")
        return EXIT_NOT_STARTED
    except OSError as exc:
        warn(f"cannot read mission {args.file}: {exc.strerror}")
        return EXIT_NOT_STARTED
    for name in unused:
        warn(f"--set {name} is not used by {args.file}")
    with connect(args, printer) as client:
        run = mission.check_mission if checking else mission.run_mission
        report = run(client, lines, printer)
    printer(mission.summary(os.path.basename(args.file), report, checking=checking))
    return report.exit_status


# ---------------------------------------------------------------------------------------------
# Command line


def _connection_options() -> argparse.ArgumentParser:
    # SUPPRESS: the options may come before or after the subcommand without one hiding the other.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--host", default=argparse.SUPPRESS, help=f"server address (default {DEFAULT_HOST})")
    common.add_argument("--port", type=int, default=argparse.SUPPRESS, help=f"text port (default {DEFAULT_PORT})")
    common.add_argument("--zmq", default=argparse.SUPPRESS, metavar="ENDPOINT",
                        help="use the ZeroMQ ROUTER at ENDPOINT (tcp://HOST:PORT) instead of the text port")
    common.add_argument("--token-file", default=argparse.SUPPRESS, metavar="F",
                        help="send `auth` with the token in F before anything else")
    common.add_argument("--timeout", type=float, default=argparse.SUPPRESS, metavar="S",
                        help=f"seconds of silence before giving up on a reply (default {CLI_TIMEOUT:g})")
    return common


def build_parser() -> argparse.ArgumentParser:
    common = _connection_options()
    parser = argparse.ArgumentParser(prog="rvs", parents=[common],
                                     description="Command-line client of the RVS (Rover Vision System) server.")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    send = commands.add_parser("send", parents=[common], help="send command lines, print the replies")
    send.add_argument("lines", nargs="+", metavar="LINE", help="one command line (quote it)")
    commands.add_parser("shell", parents=[common], help="interactive session")
    mission_parser = commands.add_parser("mission", help="run or check a mission file")
    actions = mission_parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    for action, text in (("run", "run a mission"), ("check", "validate a mission; nothing moves")):
        sub = actions.add_parser(action, parents=[common], help=text)
        sub.add_argument("file", metavar="FILE")
        sub.add_argument("--set", action="append", metavar="NAME=VALUE", help="value of ${NAME}; repeatable")
    campaign.add_parser(commands)
    remap.add_parser(commands)
    return parser


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    args = build_parser().parse_args(argv)
    for name, default in (("host", DEFAULT_HOST), ("port", DEFAULT_PORT), ("zmq", None), ("token_file", None),
                          ("timeout", CLI_TIMEOUT)):
        if not hasattr(args, name):
            setattr(args, name, default)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    printer = Printer()
    handlers = {"send": command_send, "shell": command_shell, "mission": command_mission,
                "campaign": lambda args, _printer: campaign.command_campaign(args),
                "remap": lambda args, _printer: remap.command_remap(args)}
    try:
        return handlers[args.command](args, printer)
    except StartError as exc:
        warn(str(exc))
        return EXIT_NOT_STARTED
    except RvsClientError as exc:  # the connection failed half-way
        warn(str(exc))
        return EXIT_FAILED
    except KeyboardInterrupt:
        warn("interrupted (a running job goes on on the server; `break` stops it)")
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
