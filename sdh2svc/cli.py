"""The ``sdh2svc`` command line."""

from __future__ import annotations

import argparse
import contextlib
import difflib
import errno
import json
import logging
import math
import os
import re
import signal
import sys
import traceback
from collections.abc import Callable, Coroutine, Iterator, Sequence
from datetime import UTC, datetime, timedelta
from enum import IntEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, TypeVar

from sdh2svc import __version__
from sdh2svc.config import ConfigError, Settings, clip, load_config
from sdh2svc.files import whole_file
from sdh2svc.model.friction import inside_cone, omega
from sdh2svc.model.geometry import pad_point_from_L, virtual_joint
from sdh2svc.model.kinematics import Finger, HandPose, hand_points, segment

if TYPE_CHECKING:
    import asyncio

    from sdh2svc.connect import Bench
    from sdh2svc.control.runner import Runner
    from sdh2svc.service.store import RunStore
    from sdh2svc.sim.objects import Shape
    from sdh2svc.sim.press import Press


class Exit(IntEnum):
    """The exit statuses of every command (README, *Exit status*; ``sdh2svc --help``)."""

    OK = 0
    FAILED = 1  # it ran and failed: a run that did not complete, health not OK
    USAGE = 2  # usage, invalid configuration or input (argparse's own code, too)
    NOT_FOUND = 3  # no such run, no run database
    UNAVAILABLE = 4  # I/O: the hand unreachable, a port in use, the database unusable
    BUG = 70  # an unexpected error (--debug or SDH2SVC_DEBUG=1 shows the traceback)
    INTERRUPTED = 130  # Ctrl-C
    BROKEN_PIPE = 141  # the output's reader went away (128 + SIGPIPE, as a shell reports it)


EXIT_STATUS_HELP = """\
exit status:
  0    success
  1    the operation ran and failed (a run that did not complete; health not OK)
  2    usage error, invalid configuration or input
  3    not found (no such run; no run database)
  4    cannot reach a device or use a resource (hand unreachable, port in use,
       database unusable, output file not writable)
  70   unexpected error, a bug (--debug or SDH2SVC_DEBUG=1 prints the traceback)
  130  interrupted (Ctrl-C; SIGTERM to run and campaign run)
  141  the output's reader went away (`sdh2svc runs show 7 | head`)
"""

NO_DATABASE_HINT = "set storage.db_path or run from the directory that holds data/"


class CliError(Exception):
    """A failure to report as one line on stderr with an exit status, and no traceback."""

    def __init__(self, status: Exit, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


def _fail(status: Exit, message: str) -> NoReturn:
    raise CliError(status, message)


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _no_lines_with_sim(args: argparse.Namespace) -> None:
    """--sim serves its own lines: a --dsa or --sdh beside it is a mistake, not ignored."""
    given = [f"--{name}" for name in ("dsa", "sdh") if getattr(args, name, None) is not None]
    if given:
        what = "names a real hand's line" if len(given) == 1 else "name a real hand's lines"
        _fail(Exit.USAGE, f"{' and '.join(given)} {what}: not with --sim, which serves its own")


def _add_link_args(p: argparse.ArgumentParser) -> None:
    """--dsa and --sdh: a real hand's two lines (else the configuration's ``links``)."""
    p.add_argument("--dsa", metavar="URL", type=_url_arg,
                   help="DSACON32m port or pyserial URL (real hand)")  # fmt: skip
    p.add_argument("--sdh", metavar="URL", type=_url_arg,
                   help="SDH2 port or pyserial URL (real hand)")  # fmt: skip


class _Once(argparse.Action):
    """An option that may be given once: argparse keeps the last of two silently, and a second
    ``--config`` would drop every key of the first (its ``storage.db_path`` too: another run
    database, with another e-stop latch). One file layers over the defaults; put both files'
    keys in one, or the second's as ``--set``."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:  # fmt: skip
        first = getattr(namespace, self.dest, None)
        if first is not None:
            parser.error(f"{option_string} given twice ({first!r}, {values!r}): one file "
                         "(the other's keys as --set KEY=VALUE)")  # fmt: skip
        setattr(namespace, self.dest, values)


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", action=_Once,
                   help="a TOML file overriding config/default.toml")  # fmt: skip
    p.add_argument(
        "--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
        help="override one key, e.g. --set rolling.k=3 (repeatable; beats file and environment)",
    )  # fmt: skip


def _load(args: argparse.Namespace, flags: Sequence[tuple[str, str, object]] = ()) -> Settings:
    """The configuration, with ``flags`` — (an option, the key it stands for, its value or None
    when not given) — set after --set's. A bad value is named by the option typed (``--baud
    0``), not by a --set the user never typed."""
    given = [(_typed(flag, value), f"{key}={_toml(value)}")
             for flag, key, value in flags if value is not None]  # fmt: skip
    try:
        return load_config(args.config, [*args.overrides, *(text for _, text in given)])
    except ConfigError as e:
        problems = e.problems
        for typed, text in given:  # (load_config names an override's origin "--set KEY=VALUE")
            problems = [p.replace(f"(--set {text})", f"({typed})") for p in problems]
        raise ConfigError(problems) from None


def _absolute_db(cfg: Settings) -> Settings:
    """``cfg`` with its run database in full, for every message that names it: a relative
    storage.db_path is another database in another working directory."""
    where = str(Path(cfg.storage.db_path).absolute())
    return cfg.model_copy(update={"storage": cfg.storage.model_copy(update={"db_path": where})})


def _toml(value: object) -> str:
    """``value`` as an override's TOML (a string quoted: a host is no TOML word)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return json.dumps(value) if isinstance(value, str) else repr(value)


def _typed(flag: str, value: object) -> str:
    """An option as the user typed it, near enough: ``--no-viewer``, ``--baud 0``, ``--ber 2``."""
    if isinstance(value, bool):
        return flag
    shown = repr(value).removesuffix(".0") if isinstance(value, float) else str(value)
    return f"{flag} {shown}"


def cmd_config(args: argparse.Namespace) -> int:
    """Print the effective, validated configuration as JSON."""
    data = _load(args).model_dump(mode="json")
    if data["service"]["token"]:  # as GET /api/config shows it: a terminal is often shared
        data["service"]["token"] = "***"
    print(json.dumps(data, indent=2, ensure_ascii=False))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """The hand model at one pose: contact points, object segment and friction cones."""
    cfg = _load(args)
    pad = cfg.hand.pad
    s_range = (cfg.tactile.distal.rows - 1) * cfg.tactile.texel_pitch_mm
    # φ2…φ5 within their axes' joint limits, S1 and S2 on the pad: the model has no answer
    # elsewhere (a stretched pose is still one, a pad point 1 km away is not)
    axes = (*cfg.axes.finger_axes(Finger.ONE), *cfg.axes.finger_axes(Finger.TWO))
    for name, axis in zip(("phi2", "phi3", "phi4", "phi5"), axes, strict=True):
        lo, hi, value = cfg.limits.min_deg[axis], cfg.limits.max_deg[axis], getattr(args, name)
        if not lo <= value <= hi:
            _fail(Exit.USAGE, f"--{name} {value:g}: outside axis {axis}'s joint limits "
                              f"{lo:g} … {hi:g} deg")  # fmt: skip
    for name in ("s1", "s2"):
        if not 0.0 <= getattr(args, name) <= s_range:
            _fail(Exit.USAGE, f"--{name} {getattr(args, name):g}: off the pad (0 … {s_range:g} mm)")
    pose = HandPose(*(math.radians(a) for a in (args.phi2, args.phi3, args.phi4, args.phi5)))
    x3s, vjs = [], []
    for S in (args.s1, args.s2):
        L = cfg.calibration.distance.L_from_S(S, s_range, pad)
        x3, y3 = pad_point_from_L(L, pad)
        x3s.append(x3)
        vjs.append(virtual_joint(x3, y3))
    pts = hand_points(pose, vjs[0], vjs[1], cfg.hand)
    lam, sigma = segment(pts.A, pts.B)
    wa = omega(Finger.ONE, pose.phi2 + pose.phi3, x3s[0], pts.A, pts.B, pad)
    wb = omega(Finger.TWO, pose.phi4 + pose.phi5, x3s[1], pts.B, pts.A, pad)
    alpha = cfg.rolling.alpha
    out = {
        "phi_deg": [args.phi2, args.phi3, args.phi4, args.phi5],
        "S_mm": [args.s1, args.s2],
        "A_mm": list(pts.A), "B_mm": list(pts.B), "C_mm": list(pts.C), "D_mm": list(pts.D),
        "Lambda_mm": lam, "sigma_deg": math.degrees(sigma),
        "omega_A_deg": math.degrees(wa), "omega_B_deg": math.degrees(wb),
        "inside_cone": inside_cone(wa, alpha) and inside_cone(wb, alpha),
    }  # fmt: skip
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"pose φ2…φ5 = {args.phi2}, {args.phi3}, {args.phi4}, {args.phi5} deg;  "
          f"S1 = {args.s1} mm, S2 = {args.s2} mm")  # fmt: skip
    for name in "ABCD":
        p = getattr(pts, name)
        print(f"  {name} = (y {p.y:8.2f}, z {p.z:8.2f}) mm")
    print(f"  Λ = {lam:.2f} mm   σ = {math.degrees(sigma):.2f}°")
    verdict = "inside" if out["inside_cone"] else "OUTSIDE"
    print(f"  ωA = {math.degrees(wa):.2f}°   ωB = {math.degrees(wb):.2f}°   "
          f"cone 90 ± {cfg.rolling.alpha_deg}°: {verdict}")  # fmt: skip
    return 0


def cmd_sim(args: argparse.Namespace) -> int:
    """Serve the simulated hand's two controllers (DSACON32m tactile, SDH2 joints) on ptys and
    TCP ports, for any driver — ours, SCHUNK's SDHLibrary, the ROS node — until Ctrl-C. A pad is
    pressed with --press, or by typing `press pad=1 x=10 y=12 force=2 …` (or `release`) on the
    standard input while it runs."""
    import asyncio

    from sdh2svc.connect import Simulated, simulated_hand

    cfg = _load(args, [
        ("--host", "sim.links.host", args.host), ("--boot-s", "sim.links.dsa_boot_s", args.boot_s),
        ("--ber", "sim.links.bit_error_rate", args.ber), ("--baud", "sim.links.baud", args.baud),
        ("--seed", "sim.seed", args.seed),
        ("--replace-after", "sim.replace_after_s", args.replace_after),
    ])  # fmt: skip
    obj = _object(args, cfg.sim.object)

    if (args.no_pty or not cfg.sim.links.pty) and args.no_tcp:
        _fail(Exit.USAGE, "nothing to serve: --no-tcp, and no pty (--no-pty or sim.links.pty)")
    ports = (cfg.sim.links.dsa_tcp_port if args.dsa_port is None else args.dsa_port,
             cfg.sim.links.sdh_tcp_port if args.sdh_port is None else args.sdh_port)  # fmt: skip
    if not args.no_tcp and ports[0] == ports[1] != 0:  # (a flag against the configuration's)
        _fail(Exit.USAGE, f"the DSACON32m and the SDH2 would both serve on TCP port {ports[0]}: "
                          "one port each (--dsa-port, --sdh-port)")  # fmt: skip
    if args.no_tcp and (args.dsa_port is not None or args.sdh_port is not None):
        _fail(Exit.USAGE, "--no-tcp serves no TCP port: drop --dsa-port/--sdh-port")
    # ports default to the configuration's; the lab assistant to sim.replace_after_s
    spec = Simulated(
        obj=obj,
        pty=not args.no_pty and cfg.sim.links.pty,
        tcp=not args.no_tcp,
        dsa_port=args.dsa_port,
        sdh_port=args.sdh_port,
        replace_after_s=None,
    )

    async def main() -> None:
        try:
            async with simulated_hand(cfg, spec) as bench:
                await _serve_sim(bench)
        except OSError as e:  # a port in use, an unknown --host
            why = f"{cfg.sim.links.host}: {e.strerror or e}"
            _fail(Exit.UNAVAILABLE, f"cannot serve the simulated hand on {why}")

    async def _serve_sim(bench: Bench) -> None:
        hand = bench.sim
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        for spec, (press, at) in args.press or ():
            try:
                bench.press(press, after_s=at)
            except ValueError as e:
                _fail(Exit.USAGE, f"--press {spec}: {e}")
        info = {"object": obj.name or obj.kind, "dsa": hand.urls("dsa"), "sdh": hand.urls("sdh")}
        if args.json:
            print(json.dumps(info), flush=True)
        else:
            print(f"sdh2svc sim: a simulated SCHUNK SDH2; object "
                  f"{info['object']!r} ({obj.kind}, {obj.size_mm:g} mm) waits between the "
                  f"fingertips")  # fmt: skip
            print(f"  DSACON32m (tactile): {'   '.join(info['dsa'])}")
            print(f"  SDH2 (joints):       {'   '.join(info['sdh'])}")
            for _, (press, at) in args.press or ():
                print(f"  press: {press.describe()}, {at:g} s from now")
            print("  Point a driver at one URL of each. Ctrl-C stops.", flush=True)
        _read_presses(bench, loop)
        await stop.wait()

    asyncio.run(main())
    return 0


def _press_arg(spec: str) -> tuple[str, tuple[Press, float]]:
    """``--press SPEC``: the spec as given, and its press and delay (argparse's type)."""
    from sdh2svc.sim.press import parse_spec

    try:
        return spec, parse_spec(spec)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _seconds_arg(text: str) -> float:
    """A positive, finite number of seconds (argparse's type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is no number of seconds") from None
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"{text}: a number of seconds above 0 expected")
    return value


def _digits(text: str, what: str) -> int:
    """A whole number written in the digits 0–9 only (int() would read "1_0" as 10, " 3" as
    3); argparse's error naming ``what`` it is otherwise."""
    if not (text.isascii() and text.isdigit()):
        raise argparse.ArgumentTypeError(f"{text!r}: {what} is written in the digits 0–9")
    return int(text)


def _count_arg(text: str) -> int:
    """A count: 0 or more (argparse's type)."""
    return _digits(text, "a count")


def _url_arg(text: str) -> str:
    """A device path or pyserial URL, not blank (argparse's type): an empty one would fall
    back to the configured line without a word."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty: give a device path or a pyserial URL")
    return text


def _int_arg(lo: int, hi: int, noun: str, span: str) -> Callable[[str], int]:
    """An argparse type: a whole number ``lo`` … ``hi`` (``noun``: what a number it is;
    ``span``: the range in words)."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is no {noun}") from None
        if not lo <= n <= hi:
            raise argparse.ArgumentTypeError(f"{n}: {span}")
        return n

    return parse


_port_arg = _int_arg(0, 65535, "port number", "a port is 0 … 65535")  # a TCP port
_cycles_arg = _int_arg(1, 10000, "whole number", "1 … 10000 strokes")  # rolling.cycles' range


def sim_command(bench: Bench, line: str) -> str | None:
    """One line typed into `sdh2svc sim`: ``press <spec>`` presses a pad, ``release`` lifts
    every press. Returns what to tell the user (None for a blank line); a bad line changes
    nothing."""
    from sdh2svc.sim.press import SPEC_HELP, parse_spec

    word, _, rest = line.strip().partition(" ")
    try:
        if word == "press":
            press, at = parse_spec(rest)
            bench.press(press, after_s=at)
            return f"pressing {press.describe()}" + (f", {at:g} s from now" if at else "")
        if word == "release":
            return f"released {bench.release()} press(es)"
    except ValueError as e:
        return f"bad press: {e}"
    return f"unknown command {word!r}: type `press {SPEC_HELP}` or `release`" if word else None


def _read_presses(bench: Bench, loop: Any) -> None:
    """Lines typed (or piped) into `sdh2svc sim` while it runs (:func:`sim_command`), answered
    on stderr. A thread reads them (a daemon: it never holds up the exit); the loop acts on
    them. Nothing is read unless stdin is a terminal or a pipe. A sim run in the background of
    its terminal (`sdh2svc sim &`) reads nothing until brought to the foreground: the terminal
    would stop the whole process (SIGTTIN), and the controllers with it, at its first read."""
    import signal
    import stat
    import threading
    import time

    try:
        terminal = sys.stdin.isatty()
        if not (terminal or stat.S_ISFIFO(os.fstat(sys.stdin.fileno()).st_mode)):
            return
    except (OSError, ValueError, AttributeError):  # no usable stdin
        return
    if terminal:  # a read from the background then fails (EIO) instead of stopping us
        signal.signal(signal.SIGTTIN, signal.SIG_IGN)

    def act(line: str) -> None:
        if (message := sim_command(bench, line)) is not None:
            print(f"sdh2svc sim: {message}", file=sys.stderr, flush=True)

    def read() -> None:
        while True:
            try:
                line = sys.stdin.readline()
            except OSError:  # in the background of the terminal: again once in the foreground
                time.sleep(0.5)
                continue
            if not line:
                return
            loop.call_soon_threadsafe(act, line)

    threading.Thread(target=read, name="sim-stdin", daemon=True).start()


def _object(args: argparse.Namespace, default: str = "") -> Shape:
    """The simulated object of ``--object``/``--object-file`` (else the preset ``default``)."""
    from pydantic import ValidationError

    from sdh2svc.config import format_errors
    from sdh2svc.sim.objects import ObjectSpec, get_object, load_object

    try:
        if args.object_file:
            return load_object(args.object_file)
        return get_object(args.object or default)
    except KeyError as e:  # str() of a KeyError is the repr of its argument
        _fail(Exit.USAGE, _one_line(e.args[0] if e.args else e))
    except ValidationError as e:  # before ValueError, which it is: one line per bad field
        _fail(Exit.USAGE, f"invalid object in {args.object_file}: "
                          + "; ".join(format_errors(e, ObjectSpec)))  # fmt: skip
    except OSError as e:
        _fail(Exit.USAGE, f"cannot read the object file {args.object_file}: {e.strerror or e}")
    except ValueError as e:
        where = f"the object file {args.object_file}: " if args.object_file else ""
        _fail(Exit.USAGE, where + _one_line(e))


T = TypeVar("T")


class _Stopper:
    """SIGTERM (systemd's stop, kill) and SIGINT (Ctrl-C) stop a run as the service's stop does:
    once :meth:`started` has been handed the runner, the run releases the object, ends
    ``stopped`` and its summary is printed (:attr:`asked`); before that, or at a second signal,
    the work is cancelled (the run recorded stopped, the hand left where it is). (A background
    job started by a non-interactive shell ignores SIGINT: SIGTERM is what stops it.)"""

    def __init__(self) -> None:
        self.asked = False
        self._runner: Runner | None = None
        self._task: asyncio.Task[Any] | None = None

    def started(self, runner: Runner) -> None:
        self._runner = runner

    def _signalled(self) -> None:
        if self._runner is not None and not self.asked:
            self.asked = True
            self._runner.request_stop("by Ctrl-C or SIGTERM: the fingers opened to the pre-shape")
        elif self._task is not None:
            self._task.cancel()

    async def run(self, work: Coroutine[Any, Any, T]) -> T:
        import asyncio

        loop = asyncio.get_running_loop()
        self._task = asyncio.current_task()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self._signalled)
        try:
            return await work
        finally:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)


def _debug(args: argparse.Namespace) -> bool:
    """--debug, or SDH2SVC_DEBUG set (not to 0): tracebacks and the links' log records."""
    return bool(getattr(args, "debug", False)) or os.environ.get("SDH2SVC_DEBUG", "") not in (
        "",
        "0",
    )


def _quiet_log(args: argparse.Namespace) -> None:
    """A command's failure is its one line on stderr: the links' log records (a retry, a
    reply gone missing) reached stderr beside it through logging's last resort. --debug (or
    SDH2SVC_DEBUG=1) shows them."""
    if logging.getLogger().handlers:  # a program that configured logging has them its way
        return
    if _debug(args):
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    else:
        logging.getLogger("sdh2svc").addHandler(logging.NullHandler())


def cmd_run(args: argparse.Namespace) -> int:
    """One rolling run: pre-shape, grasp, roll for N strokes, release — on the simulated hand
    (--sim) or a real one (--dsa/--sdh or the config's links). Exit status 0 only if completed."""
    import asyncio

    from sdh2svc.bus.joint import JointLinkError
    from sdh2svc.bus.tactile import TactileError
    from sdh2svc.connect import Simulated, real_hand
    from sdh2svc.service.headless import run_once
    from sdh2svc.service.store import EstopLatched, StoreError

    _quiet_log(args)
    cfg = _absolute_db(_load(args, [("--cycles", "rolling.cycles", args.cycles)]))
    obj = None
    if args.sim:
        _no_lines_with_sim(args)
        obj = _object(args, cfg.sim.object)
    elif args.object or args.object_file or args.fast:
        _fail(Exit.USAGE, "--object, --object-file and --fast need --sim")

    def progress(r: Runner) -> None:
        if args.json or not sys.stderr.isatty():
            return
        F = r.result.forces[-1] if r.result.forces else 0.0
        sig = r.result.sigmas[-1] if r.result.sigmas else 0.0
        print(f"\r{r.phase.value:10s} stroke {r.state.strokes} of {r.params.cycles}  "
              f"iteration {r.state.iteration:5d}  F {F:5.2f}  σ {sig:6.2f}°", end="",
              file=sys.stderr)  # fmt: skip

    if not args.sim:
        _say_line_from_configuration(args, cfg)
    where = Simulated(obj, fast=args.fast) if args.sim else real_hand(cfg, args.dsa, args.sdh)
    if args.sim and (latch := _latched(cfg)) is not None:  # rehearsing the e-stop: say it
        print(f"sdh2svc run: the e-stop is latched in {cfg.storage.db_path} (since "
              f"{latch['since']}); a simulated run does not obey it, a real hand's is refused",
              file=sys.stderr)  # fmt: skip

    stopper = _Stopper()
    work = stopper.run(run_once(cfg, where, progress=progress, started=stopper.started))
    try:
        if args.fast:
            from sdh2svc.sim.clock import run_fast

            summary = run_fast(work)
        else:
            summary = asyncio.run(work)
    except asyncio.CancelledError:  # a signal before the run began, or a second one
        print("sdh2svc run: interrupted " + (
            "again: the run ended at once, recorded as interrupted; the hand was left where it "
            "is and may still hold the object" if stopper.asked else "before the run began"),
            file=sys.stderr)  # fmt: skip
        return Exit.INTERRUPTED
    except StoreError as e:
        _fail(Exit.UNAVAILABLE, str(e))
    except EstopLatched as e:
        _fail(Exit.FAILED, str(e))
    except (JointLinkError, TactileError, OSError) as e:
        _fail(Exit.UNAVAILABLE, f"cannot reach the hand: {_one_line(e)} {_lines_hint(args, e)}")
    if args.json:
        print(json.dumps(summary))
    else:
        if sys.stderr.isatty():  # end the progress line
            print(file=sys.stderr)
        f = summary["force"]
        print(f"run {summary['run_id']}: {summary['status']} {summary['message']}".rstrip())
        print(
            f"  strokes {summary['strokes']}, iterations {summary['iterations']}, "
            f"reversals {sum(summary['reversals'].values())}, "
            f"Λ at grasp {_mm(summary['lambda_initial_mm'])}"
        )
        if f["mean"] is not None:
            print(
                f"  F mean {f['mean']:.2f} (sd {f['sd'] or 0:.2f}, {f['min']:.2f}…{f['max']:.2f})"
                f", loop {summary['loop_hz'] or 0:.1f} Hz"
            )
        if rec := summary.get("recognition"):
            print(f"  {_recognised(rec)}")
        if truth := summary.get("truth"):
            print(f"  simulation truth: {truth['object']} ({truth['size_mm']:.1f} mm), turned over "
                  f"{truth['rotation_range_deg']:.1f}°, {truth['slips']} slips"
                  f"{', dropped' if truth['dropped'] else ''}")  # fmt: skip
    if summary["status"] == "completed":
        if summary.get("not_recorded"):  # the run went well; its record did not
            said = _one_line(summary["message"])
            print(f"sdh2svc run: run {summary['run_id']} completed; {said}", file=sys.stderr)
        return Exit.OK
    # the summary is the output (stdout); the failure is also the one line on stderr
    why = _one_line(summary["message"]) or (
        "by Ctrl-C or SIGTERM, as the service's stop: the fingers opened to the pre-shape"
        if stopper.asked and summary["status"] == "stopped" else "no message")  # fmt: skip
    print(f"sdh2svc run: run {summary['run_id']} {summary['status']}: {why}",
          file=sys.stderr)  # fmt: skip
    return Exit.INTERRUPTED if stopper.asked else Exit.FAILED


def _say_line_from_configuration(args: argparse.Namespace, cfg: Settings) -> None:
    """A real hand's run given one of --dsa/--sdh takes the other from the configuration
    (/dev/ttyS0 or ttyS1 by default), which the lab that typed one line may not mean: said."""
    for flag, other, key, line in (("dsa", "sdh", "dsa_url", "tactile"),
                                   ("sdh", "dsa", "sdh_url", "joint")):  # fmt: skip
        if getattr(args, flag) is None and getattr(args, other) is not None:
            print(f"sdh2svc run: --{flag} not given: the {line} line is links.{key} = "
                  f"{getattr(cfg.links, key)} from the configuration", file=sys.stderr)  # fmt: skip


def _lines_hint(args: argparse.Namespace, e: BaseException) -> str:
    """What to check when the hand cannot be reached. The joint line is opened first: when it
    greets not as an SDH2 ("SDH not connected", the joint link's word: a DSACON32m is silent
    to `ver` unless it streams) on lines the user gave both of, they may be swapped — asked, as
    a hint. (A tactile handshake failing comes after an SDH2 answered on --sdh: not a swap.)"""
    from sdh2svc.bus.joint import JointLinkError

    said = str(e)
    if (args.dsa is not None and args.sdh is not None and isinstance(e, JointLinkError)
            and "SDH not connected" in said and "swapped" not in said):  # fmt: skip
        return "(are --dsa and --sdh swapped?)"
    return "(check --sdh/--dsa or links.sdh_url/dsa_url)"


def _latched(cfg: Settings) -> dict[str, Any] | None:
    """The e-stop latch in the run database, if there is one and it can be read."""
    import sqlite3

    from sdh2svc.service.store import RunStore, StoreError

    try:
        store = RunStore(cfg.storage.db_path, create=False,
                         busy_timeout_s=cfg.storage.busy_timeout_s)  # fmt: skip
    except StoreError:  # (NoDatabase among them): nothing latched that this run could read
        return None
    try:
        return store.estop_latch()
    except sqlite3.Error:
        return None
    finally:
        store.close()


# what each class's two sizes are (control.recognition.Recognition), as the dashboard names them
_SIZES = {"circle": ("radius", None), "ellipse": ("semi-axes", "and"),
          "box": ("side held", None), "stick": ("length", "diameter"),
          "polygon": ("circumradius", None)}  # fmt: skip


def _recognised(rec: dict[str, Any]) -> str:
    """The recognition's summary in one line, its sizes named (they are radii, semi-axes…)."""
    cls = rec.get("object_class")
    if cls:
        first, second = _SIZES.get(cls, ("size", "and"))
        a, b = rec.get("size_a_mm"), rec.get("size_b_mm")
        size = f"{first} {a:.1f} mm" if a is not None else ""
        if b is not None and second is not None:
            size += f" {second} {b:.1f} mm" if second == "and" else f", {second} {b:.1f} mm"
        what = (f"recognised {'an' if cls[0] in 'aeiou' else 'a'} {cls} "
                f"({rec.get('confidence') or 0:.0%}{'; ' + size if size else ''})")  # fmt: skip
    else:
        what = "no class recognised"
    turned = rec.get("rotation_range_deg")
    if turned is not None:
        end = rec.get("rotation_deg") or 0.0
        what += f", estimated to turn over {turned:.1f}° (at the end {end:.1f}°)"
    if failed := rec.get("failed"):
        what += f"; the recognition failed at iteration {failed['iteration']}: {failed['message']}"
    return what


def _mm(value: float | None) -> str:
    return "—" if value is None else f"{value:.1f} mm"


def cmd_serve(args: argparse.Namespace) -> int:
    """The service: REST/WebSocket API, dashboard and 3-D view, on the embedded simulated hand
    (--sim) or a real one (--dsa/--sdh or the config's links). Ctrl-C/SIGTERM stop motion first."""
    import asyncio

    from sdh2svc.connect import Simulated, real_hand
    from sdh2svc.service.server import ExposureError, StartError, serve, setup_logging

    setup_logging(args.log_format, args.log_level)  # first: a bad configuration is logged too
    cfg = _load(args, [
        ("--host", "service.host", args.host), ("--port", "service.port", args.port),
        ("--viser-port", "service.viser_port", args.viser_port),
        ("--no-viewer", "service.viewer", False if args.no_viewer else None),
    ])  # fmt: skip
    obj = None
    if args.sim:
        _no_lines_with_sim(args)
    if args.object or args.object_file:
        if not args.sim:
            _fail(Exit.USAGE, "--object and --object-file need --sim")
        obj = _object(args)
    # no lab assistant: the service puts the object back itself before every run
    # a service waits for its hand (powered on after the PC, an adapter plugged in later): its
    # status says why a line is not up, its e-stop is owed to the hand until it answers
    where = Simulated(obj) if args.sim else real_hand(cfg, args.dsa, args.sdh, patient=True)
    try:
        return asyncio.run(serve(cfg, where, announce_json=args.json))
    except ExposureError as e:
        _fail(Exit.USAGE, str(e))
    except StartError as e:
        _fail(Exit.UNAVAILABLE, _one_line(e))


def status_url(url: str) -> str:
    """The service's status URL from what ``health --url`` was given: its base URL
    (:func:`sdh2svc.client.service_url`: ``http://`` when no scheme is given) or the full
    ``…/api/status``."""
    from urllib.parse import urlsplit, urlunsplit

    from sdh2svc.client import service_url

    try:
        parts = urlsplit(service_url(url))
    except ValueError as e:
        _fail(Exit.USAGE, f"--url {e} (or …/api/status)")
    path = parts.path.rstrip("/")
    if not path.endswith("/api/status"):
        path += "/api/status"
    return urlunsplit((parts.scheme, parts.netloc, path, "", ""))


def _local_url(cfg: Settings) -> str:
    """The base URL of the service this configuration describes, from this machine (a service
    listening on every address is reached on the loopback)."""
    host = cfg.service.host if cfg.service.host not in ("0.0.0.0", "::") else "127.0.0.1"
    host = f"[{host}]" if ":" in host else host
    return f"http://{host}:{cfg.service.port}"


def cmd_health(args: argparse.Namespace) -> int:
    """Exit 0 if the service answers GET /api/status with both links connected (HEALTHCHECK);
    1 if it does not answer, answers something else, or reports a link down."""
    import urllib.error
    import urllib.parse
    import urllib.request

    cfg = _load(args)
    url = status_url(args.url) if args.url else f"{_local_url(cfg)}/api/status"
    # a service on this machine is asked directly: urllib would send even a loopback request
    # to the proxy of http_proxy (a lab PC's, a container's), which answers for another host
    # or not at all, and the check would fail naming the service
    from sdh2svc.hosts import is_loopback

    direct = is_loopback(urllib.parse.urlsplit(url).hostname)
    opener = urllib.request.build_opener(*([urllib.request.ProxyHandler({})] if direct else []))
    try:
        with opener.open(url, timeout=args.timeout) as r:
            status = json.load(r)
    except urllib.error.HTTPError as e:
        _fail(Exit.FAILED, f"{url} answered HTTP {e.code} {e.reason}")
    except urllib.error.URLError as e:
        why = getattr(e.reason, "strerror", None) or e.reason
        _fail(Exit.FAILED, f"no answer from {url}: {why}")
    except (OSError, ValueError) as e:  # a timeout, a reset; not JSON
        _fail(Exit.FAILED, f"no usable answer from {url}: {_one_line(e) or type(e).__name__}")
    try:
        down = [name for name, up in status["hand"]["connected"].items() if not up]
    except (KeyError, TypeError, AttributeError):
        _fail(Exit.FAILED, f"{url} did not answer like sdh2svc's /api/status")
    if down:
        _fail(Exit.FAILED, f"link(s) down: {', '.join(down)} ({url})")
    print(f"ok: {url}")
    return Exit.OK


def cmd_estop(args: argparse.Namespace) -> int:
    """The e-stop latch kept in the run database (what a restarted service re-applies, and what
    `run` on a real hand refuses to start under): show it, latch it, or release it. ``--latch``
    e-stops the service this configuration names through its API (POST /api/estop) when it
    keeps its runs in this database; any running service or real-hand `run` keeping its runs
    here stops its hand within a second of the latch on disk and says so, which this command
    waits for. Release a running service through its API (POST /api/estop/release)."""
    import sqlite3

    from sdh2svc.service.store import NoDatabase, RunStore, StoreError, opened_elsewhere

    cfg = load_config(args.config, args.overrides)
    # where the latch is kept, in full: a relative storage.db_path is another database (and
    # another latch) in another working directory
    where = Path(cfg.storage.db_path).absolute()
    new = args.latch and not where.exists()
    try:
        store = RunStore(
            cfg.storage.db_path, create=args.latch, busy_timeout_s=cfg.storage.busy_timeout_s
        )
    except NoDatabase:
        if args.release:
            _fail(Exit.NOT_FOUND, f"no run database at {where}: nothing latched")
        print(f"released (no run database at {where} yet)")
        return Exit.OK
    except StoreError as e:
        _fail(Exit.UNAVAILABLE, _one_line(e))
    others = opened_elsewhere(where) if args.latch or args.release else None
    # beside a running service, its own e-stop stops the hand: asked first, the disk after
    via = _estop_service(cfg, store, shared=others is not None) if args.latch else None
    if args.release and others:
        # a running service keeps its own latch: released on disk only, it would stay latched
        # and say the latch is on disk, while a restart came up released
        store.close()
        _fail(Exit.FAILED, f"{others}: not released — release a running service through its "
              "API (POST /api/estop/release), or release here once nothing else has the "
              "database open")  # fmt: skip
    try:
        if args.latch:
            store.latch_estop("latched from the command line")
        elif args.release:
            store.release_estop()
        latch = store.estop_latch()
    except sqlite3.Error as e:  # locked by another program past the busy timeout, a bad disk
        _fail(Exit.UNAVAILABLE, f"the run database {where} is unusable: {e}")
    finally:
        store.close()
    said = "released" if latch is None else f"latched since {latch['since']}: {latch['reason']}"
    print(f"{said} (in {where})")
    if new:  # a mistyped path latches a database no service or run reads: loudly
        print(f"sdh2svc estop: there was no run database at {where}: a new one was made for "
              "the latch; a service or `sdh2svc run` with another storage.db_path does not see "
              "it", file=sys.stderr)  # fmt: skip
    if via is not None and via[1] is None:  # the service the configuration names: not here
        print(f"sdh2svc estop: the service at {via[0]} keeps its runs in another database, so "
              "this latch does not stop it: it was NOT stopped — stop it through its API (POST "
              "/api/estop) or the dashboard, or latch the database it uses (--set "
              "storage.db_path=…)", file=sys.stderr)  # fmt: skip
        if others:  # a program on this database may still stop a hand of its own
            _estop_taken(cfg, where, latch, others)
        return Exit.FAILED
    if via is not None:
        url, answer = via
        assert answer is not None
        if answer.get("hand_reached") is False:
            print(f"sdh2svc estop: the service at {url}, which keeps its runs in this database, "
                  "latched its e-stop, but the hand has not confirmed it: "
                  f"{answer.get('detail') or 'the joint line is down or silent'} — stop the hand "
                  "another way now", file=sys.stderr)  # fmt: skip
            return Exit.FAILED
        print(f"the service at {url}, which keeps its runs in this database, e-stopped the "
              "hand: release it through its API (POST /api/estop/release) or the "
              "dashboard")  # fmt: skip
        return Exit.OK
    if args.latch and others:  # a service or a real-hand run reading it stops its hand
        return _estop_taken(cfg, where, latch, others)
    return Exit.OK


def _estop_taken(cfg: Settings, where: Path, latch: dict[str, str] | None, others: str) -> int:
    """Wait for the programs reading the database to say they stopped their hand for the
    latch just written (a service or a real-hand `sdh2svc run` does within a second): exit 0
    once one has and its hand confirmed, 1 otherwise."""
    import sqlite3
    import time

    from sdh2svc.service.latch import TAKE_WAIT_S
    from sdh2svc.service.store import RunStore, StoreError

    takers: list[dict[str, Any]] = []
    end = time.monotonic() + TAKE_WAIT_S
    try:
        store = RunStore(where, create=False, busy_timeout_s=cfg.storage.busy_timeout_s)
    except StoreError:
        store = None
    try:
        while store is not None and latch is not None and not takers and time.monotonic() < end:
            time.sleep(0.1)
            with contextlib.suppress(sqlite3.Error):
                takers = store.estop_takers(latch["since"])
    finally:
        if store is not None:
            store.close()
    for t in takers:
        said = "stopped its hand" if t["hand_reached"] else (
            "latched its e-stop, but its hand has not confirmed it (the joint line is down or "
            "silent): it sends the power-off when the line answers — stop the hand another way "
            "now")  # fmt: skip
        if t["hand_reached"]:
            print(f"{t['program']}, which reads this database, {said} (at {t['at']})")
        else:
            print(f"sdh2svc estop: {t['program']}, which reads this database, {said} (at "
                  f"{t['at']})", file=sys.stderr)  # fmt: skip
    if takers:
        return Exit.OK if all(t["hand_reached"] for t in takers) else Exit.FAILED
    print(f"sdh2svc estop: {others}, and no program reading it stopped a hand for the latch "
          f"within {TAKE_WAIT_S:g} s (a running service or a real hand's `sdh2svc run` does "
          "within a second; a reader, a simulated run or an older version does not): the hand "
          "was NOT stopped: stop it where it is driven — a service through its API (POST "
          "/api/estop) or the dashboard's E-STOP, a headless `sdh2svc run` with Ctrl-C in its "
          "terminal", file=sys.stderr)  # fmt: skip
    return Exit.FAILED


def _estop_service(
    cfg: Settings, store: RunStore, *, shared: bool
) -> tuple[str, dict[str, Any] | None] | None:
    """E-stop the running service this configuration names (POST /api/estop at its host and
    port) when it keeps its runs in ``store``'s database: another program has the database
    open (``shared``) and the service's newest run is the database's newest, or neither has
    any (a service on another database drives another hand). Its URL and answer; its URL and
    None when it answered but keeps its runs elsewhere; None when no service answered there."""
    import sqlite3

    from sdh2svc.client import ESTOP_TIMEOUT_S, ApiError, Client, Unreachable

    url = _local_url(cfg)
    try:
        mine = [(r["id"], r["started_at"]) for r in store.run_page(1)[0]]
        with Client(url, token=cfg.service.token or None, timeout=ESTOP_TIMEOUT_S) as c:
            theirs = [(r["id"], r["started_at"]) for r in c.runs(limit=1)]
            if not shared or theirs != mine:
                return url, None
            return url, c.estop()
    except (sqlite3.Error, ApiError, Unreachable, KeyError, TypeError, ValueError):
        return None


RUN_IDS = range(-(2**63), 2**63)  # SQLite's integers: any other ID names no run


def _run_id(text: str) -> int:
    """A run ID as the API takes it: the digits 0–9 only."""
    return _digits(text, "a run ID")


def _when_arg(text: str) -> datetime:
    """A moment (argparse's type): ``30d`` or ``12h`` ago, or an ISO date or date and time
    (local time unless it gives its offset)."""
    t = text.strip()
    now = datetime.now().astimezone()
    try:
        if t[:-1].isascii() and t[:-1].isdigit() and t[-1:] in ("d", "h"):
            return now - timedelta(**{"days" if t[-1] == "d" else "hours": int(t[:-1])})
        when = datetime.fromisoformat(t)
    except OverflowError:  # an age beyond the calendar (1000000d)
        raise argparse.ArgumentTypeError(f"{text!r}: further back than the calendar goes") from None
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give a date (2026-11-30), a date and time (2026-11-30T14:00) or an age "
            "(30d, 12h)"
        ) from None
    return when.astimezone()  # a time without its offset is local


def cmd_runs(args: argparse.Namespace) -> int:
    """Recorded runs: list them, show one, export one as CSV or MCAP; delete runs, prune the
    older ones (--keep N, --before WHEN), vacuum the file so that it shrinks. Never creates a
    database."""
    import sqlite3

    from sdh2svc.service.store import NoDatabase, RunStore, StoreError, stray_logs

    cfg = _absolute_db(_load(args))
    ids = args.id
    if args.action in ("show", "export", "delete") and not ids:
        _fail(Exit.USAGE, f"{args.action}: which run? (give its ID)")
    if args.action in ("show", "export") and len(ids) > 1:
        _fail(Exit.USAGE, f"{args.action}: one run at a time ({len(ids)} IDs given)")
    if args.action == "prune" and args.keep is None and args.before is None:
        _fail(Exit.USAGE, "prune: which runs? (give --keep N, --before WHEN, or both)")
    # what only another action takes is a mistake here, not dropped without a word
    named = f"the run ID{'s' if len(ids) > 1 else ''} {', '.join(map(str, ids))}"
    extra = [what for what, given, takes in (
        (named, bool(ids), ("show", "export", "delete")),
        ("--format", args.format is not None, ("export",)),
        ("--output", args.output is not None, ("export",)),
        ("--keep", args.keep is not None, ("prune",)),
        ("--before", args.before is not None, ("prune",)),
        ("--dry-run", args.dry_run, ("delete", "prune")),
        ("--vacuum", args.vacuum, ("delete", "prune")),
    ) if given and args.action not in takes]  # fmt: skip
    if extra:
        _fail(Exit.USAGE, f"{', '.join(extra)}: not with runs {args.action}")
    args.format = _export_format(args.format, args.output)
    args.id = ids[0] if ids else None
    try:
        store = RunStore(
            cfg.storage.db_path, create=False, busy_timeout_s=cfg.storage.busy_timeout_s
        )
    except NoDatabase as e:
        _fail(Exit.NOT_FOUND, f"{e} ({NO_DATABASE_HINT})")
    except StoreError as e:
        _fail(Exit.UNAVAILABLE, _one_line(e))
    try:
        if args.action in ("delete", "prune", "vacuum"):
            return _retention(args, store, ids)
        return _runs(args, store, cfg)
    except sqlite3.Error as e:
        _fail(Exit.UNAVAILABLE, f"run database {store.path}: {_one_line(e)}"
                                f"{stray_logs(Path(store.path))}")  # fmt: skip
    finally:
        store.close()


def _megabytes(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def _retention(args: argparse.Namespace, store: Any, ids: list[int]) -> int:
    """``runs delete``, ``runs prune`` and ``runs vacuum``: what goes (or would go), and what
    it gives back."""
    from sdh2svc.service.store import StoreError

    if args.action == "delete":
        missing = [i for i in ids if i not in RUN_IDS or store.run(i) is None]
        if missing:
            _fail(Exit.NOT_FOUND, f"no run {', '.join(map(str, missing))} in {store.path} "
                                  "(nothing deleted)")  # fmt: skip
        doomed = list(dict.fromkeys(ids))
    elif args.action == "prune":
        doomed = store.prunable(args.keep, args.before)
        print(f"prune: {_prune_rule(args.keep, args.before)}", file=sys.stderr)
    else:
        doomed = []
    try:
        if args.action != "vacuum":
            if args.dry_run:
                said = f"{_n_runs(doomed)}: {_id_ranges(doomed)}" if doomed else "no run"
                if doomed or args.vacuum:  # (with nothing to delete, nothing is written)
                    with _write_protected(store, f"would delete {said}, but"):
                        store.check_writable()  # as the delete itself would say
                store.refuse_recording(doomed)
                print(f"would delete {said}", file=sys.stderr)
                return Exit.OK
            if doomed:
                with _write_protected(store, "nothing deleted:"):
                    done = store.delete_runs(doomed)
                _, free = store.size()
                print(f"deleted {_n_runs(done)}: {_id_ranges(done)}; {_megabytes(free)} of "
                      f"{store.path} now free for new runs", file=sys.stderr)  # fmt: skip
            else:
                print("no run to delete", file=sys.stderr)
        if args.action == "vacuum" or args.vacuum:
            before, _ = store.size()
            with _write_protected(store, "not vacuumed:"):
                store.vacuum()
            after, _ = store.size()
            print(f"{store.path}: {_megabytes(before)} → {_megabytes(after)}", file=sys.stderr)
    except StoreError as e:  # RunBusy: a run being recorded, the file open elsewhere
        _fail(Exit.FAILED, _one_line(e))
    return Exit.OK


@contextlib.contextmanager
def _write_protected(store: Any, said: str) -> Iterator[None]:
    """A write refused because this process may not write the file, its folder, or a log left
    beside it (SQLite's "attempt to write a readonly database"), said as such after ``said``;
    exit 4."""
    import sqlite3

    from sdh2svc.service.store import read_only, stray_logs

    try:
        yield
    except sqlite3.OperationalError as e:
        if not read_only(e):
            raise
        path = Path(store.path)
        if stray := stray_logs(path):
            why = f"{path} cannot be written{stray}"
        elif not os.access(path, os.W_OK):
            why = f"{path} is write-protected: make it writable to delete runs or vacuum it"
        elif not os.access(path.parent, os.W_OK):
            why = (f"{path} is in a write-protected folder: make the folder writable to "
                   "delete runs or vacuum it")  # fmt: skip
        else:
            why = f"{path} cannot be written from here: {_one_line(e)}"
        _fail(Exit.UNAVAILABLE, f"{said} {why}")


def _prune_rule(keep: int | None, before: datetime | None) -> str:
    """Which runs a prune takes, the moment in UTC as `runs list` shows start times (WHEN is
    read in local time unless it gives its offset)."""
    parts = [f"runs beyond the newest {keep}"] if keep is not None else []
    if before is not None:
        utc = before.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S+0000")
        local = before.astimezone().strftime("%Y-%m-%d %H:%M:%S %Z")
        parts.append(f"runs started before {utc} ({local})")
    return " and ".join(parts) + " (a run being recorded is left out)"


def _n_runs(runs: list[Any]) -> str:
    return f"{len(runs)} run{'' if len(runs) == 1 else 's'}"


def _id_ranges(ids: list[int]) -> str:
    """Run IDs as ranges: 1–5, 8, 10–11."""
    parts: list[tuple[int, int]] = []
    for i in sorted(ids):
        if parts and parts[-1][1] == i - 1:
            parts[-1] = (parts[-1][0], i)
        else:
            parts.append((i, i))
    return ", ".join(str(a) if a == b else f"{a}–{b}" for a, b in parts)


def _run_line(r: dict[str, Any]) -> str:
    """A run in `runs list`: ID, start, status, iterations, the simulated object, and its
    message: why a run that did not complete ended, what of its record is missing."""
    obj = r["meta"].get("object")
    name = (obj.get("name") or obj.get("kind") if isinstance(obj, dict) else obj) or "-"
    why = _one_line((r["summary"] or {}).get("message") or "")  # (a completed run's: its record)
    line = f"{r['id']:5d}  {r['started_at']}  {r['status']:11s}  {r['iterations']:6d} iterations"
    return f"{line}  {name:<10s}  {why}".rstrip()


def _export_format(given: str | None, output: str | None) -> str:
    """--format, or the one --output's name says (``.mcap``, ``.csv``) — as the client's export
    takes it. A name that says the other format is a usage error: a CSV named .mcap is a file
    no MCAP reader opens; so is a file named neither (``r1.txt``): its format would be a guess.
    Standard output (no -o, ``-``), a device and a folder take CSV unless --format says
    otherwise (a folder is then refused as no file, exit 4)."""
    suffix = Path(output).suffix if output else ""
    said = suffix.lower().lstrip(".") if suffix.lower() in (".csv", ".mcap") else ""
    if given and said and said != given:
        _fail(Exit.USAGE, f"--format {given} into {output}: its name says {said} (rename it, or "
                          f"drop --format)")  # fmt: skip
    if not (given or said) and output and output != "-" and _a_file_to_write(output):
        what = f"its suffix {suffix}" if suffix else "no suffix"
        _fail(Exit.USAGE, f"-o {output}: {what} says no export format; .csv or .mcap does (name "
                          "it so, or give --format csv or --format mcap)")  # fmt: skip
    return given or said or "csv"


def _a_file_to_write(output: str) -> bool:
    """-o names a regular file, or none yet: one the export makes (a device, a pipe or a
    folder is written, or refused, as it is)."""
    path = Path(output)
    return not path.exists() or path.is_file()


def _runs(args: argparse.Namespace, store: Any, cfg: Settings) -> int:
    if args.action == "list":
        runs = store.runs()
        for r in runs:
            print(_run_line(r))
        on_disk, free = store.size()
        print(f"{_n_runs(runs)} in {store.path}: {_megabytes(on_disk)}, {_megabytes(free)} of "
              "it free for new runs (`runs prune` deletes old runs)", file=sys.stderr)  # fmt: skip
        return Exit.OK
    run = store.run(args.id) if args.id in RUN_IDS else None
    if run is None:
        _fail(Exit.NOT_FOUND, f"no run {args.id} in {store.path}")
    if args.action == "show":
        print(json.dumps(store.record(args.id), indent=2, ensure_ascii=False))
        return Exit.OK
    if args.output == "-":  # standard output, as the convention has it (MCAP too: to a pipe)
        path = None
    else:
        path = args.output or (None if args.format == "csv" else f"run-{args.id}.mcap")
    if path is None and sys.stdout is None:  # started with its standard output closed
        _fail(Exit.UNAVAILABLE, "cannot write stdout: it is closed (give --output FILE)")
    try:
        with _sigterm_as_ctrl_c():  # `kill`: as Ctrl-C, the file kept whole
            _export(args, store, cfg, run, path)
    except BrokenPipeError:  # the reader had enough (`… | head`): as every command, 141
        _quiet_stdout()
        return Exit.BROKEN_PIPE
    except OSError as e:
        _fail(Exit.UNAVAILABLE, f"cannot write {path or 'stdout'}: {e.strerror or e}")
    except KeyboardInterrupt:
        if path:
            print(f"sdh2svc runs: interrupted; {path} not written (a file there before is as it "
                  "was)", file=sys.stderr)  # fmt: skip
        raise
    return Exit.OK


def _progress_line(text: str, *, last: bool = False) -> None:
    """``text`` over the terminal's progress line (only when stderr is a terminal); ``last``
    ends the line."""
    if sys.stderr.isatty():
        print(f"\r{text}", end="\n" if last else "", file=sys.stderr, flush=True)


def _export(args: argparse.Namespace, store: Any, cfg: Settings, run: dict[str, Any],
            path: str | None) -> None:  # fmt: skip
    """Export run ``args.id`` as CSV or MCAP, to ``path`` (written whole) or standard output."""
    if args.format == "csv":
        if path is None:
            store.export_csv(args.id, sys.stdout)
        else:
            with whole_file(path, binary=False) as out:
                store.export_csv(args.id, out)
        return
    from sdh2svc.service.store import recorded_settings

    try:  # before the file is opened: a refused run leaves no empty file behind
        recorded_settings(run, cfg)
    except ConfigError as e:
        _fail(Exit.USAGE, f"run {args.id} cannot be drawn by this version: "
                          + "; ".join(e.problems))  # fmt: skip

    iterations = 0  # written so far: the last progress call has them all

    def progress(done: int, total: int) -> None:  # a run of hours takes minutes
        nonlocal iterations
        iterations = done
        _progress_line(f"run {args.id}: {done}/{total} iterations written")

    if path is None:  # MCAP is written with seeks back, which a pipe cannot take
        import shutil
        import tempfile

        with tempfile.TemporaryFile() as fh:
            n = store.export_mcap(args.id, fh, cfg, progress)
            fh.seek(0)
            shutil.copyfileobj(fh, sys.stdout.buffer)
        sys.stdout.flush()
    else:
        with whole_file(path, binary=True) as out:
            n = store.export_mcap(args.id, out, cfg, progress)
    if sys.stderr.isatty():  # end the progress line (the run may have grown since it was counted)
        print(file=sys.stderr)
    print(f"{path or 'stdout'}: {iterations} iterations in {n} messages", file=sys.stderr)


def _quiet_stdout() -> None:
    """Point stdout at /dev/null: Python's flush of a closed pipe at exit would complain."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


def cmd_campaign(args: argparse.Namespace) -> int:
    """Campaigns: run every case of a suite (one fast simulated run each, judged from the
    simulation's truth) into OUT/results.parquet; report on one; compare two; generate a new
    suite from a seed. `run` is resumable: the same command on the same --out runs only the
    cases not yet recorded."""

    from sdh2svc.campaign.run import CampaignError

    if args.action != "generate" and (args.seed is not None or args.cases is not None):
        _fail(Exit.USAGE, "--seed and --cases go with generate only")
    if args.action in ("run", "report") and args.output is not None:
        where = "--out DIR" if args.action == "run" else "DIR/report.md, always"
        _fail(Exit.USAGE, f"-o/--output goes with compare and generate only ({args.action} "
                          f"writes into {where})")  # fmt: skip
    try:
        if args.action == "run":
            return _campaign_run(args)
        if args.action == "generate":
            return _campaign_generate(args)
        if args.action == "report":
            from sdh2svc.campaign.report import write_report

            _only_for(args, "report")
            try:
                path = write_report(Path(args.dir))
            except PermissionError as e:  # (a missing folder is NOT_FOUND, below)
                _fail(Exit.UNAVAILABLE, f"cannot write the report: {e.filename}: {e.strerror}")
            print(path)
            return Exit.OK
        from sdh2svc.campaign.report import compare

        _only_for(args, "compare")
        if args.dir_b is None:
            _fail(Exit.USAGE, "compare needs two campaign folders: DIR_A DIR_B")
        text = compare(Path(args.dir), Path(args.dir_b))
        out = Path(args.output) if args.output else Path(args.dir_b) / "compare.md"
        try:  # the file first: a reader that goes away (`| head`) must not cost it
            out.write_text(text)
        except OSError as e:
            _fail(Exit.UNAVAILABLE, f"cannot write {out}: {e.strerror or e}")
        print(text, end="")
        print(f"written to {out}", file=sys.stderr)
        return Exit.OK
    except CampaignError as e:
        _fail(Exit(e.status), _one_line(e))
    except FileNotFoundError as e:
        _fail(Exit.NOT_FOUND, _one_line(e))


def _only_for(args: argparse.Namespace, action: str) -> None:
    """``report``, ``compare`` and ``generate`` take none of ``run``'s options: given, they are
    mistakes (a --set the user thinks applies), not silently dropped; ``report`` takes one
    folder. (A suite is generated from the packaged configuration alone: the same seed, the
    same cases.)"""
    if action == "report" and args.dir_b is not None:
        _fail(Exit.USAGE, f"report takes one campaign folder, not {clip(args.dir_b)!r} too")
    given = [flag for flag, value in (("--set", args.overrides), ("--config", args.config),
                                      ("--workers", args.workers), ("--ray", args.ray),
                                      ("--out", args.out))
             if value is not None and value != []]  # fmt: skip
    if given:
        _fail(Exit.USAGE, f"{', '.join(given)}: options of campaign run, not of {action}")


def _campaign_generate(args: argparse.Namespace) -> int:
    """A new suite of ``--cases`` generated cases from ``--seed``: the same seed and count, the
    same cases (a suite of objects none of the packaged suites holds, e.g. to check a change on
    objects it was not chosen on)."""

    from sdh2svc.campaign.case import SEED_MAX
    from sdh2svc.campaign.generate import GENERATED, generated_id, generated_suite

    name = args.dir
    if args.dir_b is not None:
        _fail(Exit.USAGE, f"generate takes one suite name, not {clip(args.dir_b)!r} too")
    _only_for(args, "generate")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", name):
        _fail(Exit.USAGE, f"suite name {clip(name)!r}: letters, digits, '_', '.', '-' (at most "
                          "64, starting with a letter or digit)")  # fmt: skip
    if args.seed is None or args.cases is None:
        _fail(Exit.USAGE, "generate needs --seed S and --cases N (the same seed and count, "
                          "the same cases)")  # fmt: skip
    if not 1 <= args.cases <= 10_000:
        _fail(Exit.USAGE, f"--cases {args.cases}: 1 to 10000 (about 35 ms each to generate)")
    if not 0 <= args.seed <= SEED_MAX:
        _fail(Exit.USAGE, f"--seed {clip(str(args.seed))}: 0 to {SEED_MAX}")
    longest = max((generated_id(f"{name}-", f, args.cases - 1) for f in GENERATED), key=len)
    if len(longest) > 64:
        _fail(Exit.USAGE, f"suite name {clip(name)!r}: at most {64 - len(longest) + len(name)} "
                          f"characters for {args.cases} cases (its case ids, such as "
                          f"{clip(longest)!r}, are at most 64)")  # fmt: skip
    out = Path(args.output or f"{name}.json")
    if out.exists():
        _fail(Exit.USAGE, f"{out} exists: a suite is never rewritten (give another -o FILE)")

    def progress(done: int, n: int) -> None:
        if done == n or done % 10 == 0:
            _progress_line(f"generating {done}/{n} cases", last=done == n)

    description = f"{args.cases} generated cases, seed {args.seed}"
    suite = generated_suite(name, args.seed, args.cases, description=description,
                            prefix=f"{name}-", progress=progress)  # fmt: skip
    try:
        suite.dump(out)
    except OSError as e:
        _fail(Exit.UNAVAILABLE, f"cannot write {out}: {e.strerror or e}")
    print(f"{out}: suite {name!r}, {args.cases} cases from seed {args.seed}")
    return Exit.OK


def _campaign_run(args: argparse.Namespace) -> int:

    from sdh2svc.campaign.case import load_suite
    from sdh2svc.campaign.run import run_campaign

    if args.dir_b is not None:
        _fail(Exit.USAGE, f"run takes one suite, not {args.dir_b!r} too")
    if args.workers is not None and args.workers < 1:
        _fail(Exit.USAGE, f"--workers {args.workers}: at least 1")
    suite = load_suite(args.dir)
    out = Path(args.out or f"campaigns/{suite.name}")
    try:
        with _sigterm_as_ctrl_c():  # `kill`: stopped as by Ctrl-C
            outcome = run_campaign(suite, out, workers=args.workers, ray_address=args.ray,
                                   overrides=args.overrides, config_path=args.config,
                                   progress=not args.quiet)  # fmt: skip
    except KeyboardInterrupt:
        print(f"sdh2svc campaign: interrupted; every finished case is in {out}: the same "
              "command goes on with the rest", file=sys.stderr)  # fmt: skip
        raise
    n = outcome.total
    print(f"{out}: {n} cases ({outcome.skipped} already there, {outcome.ran} run in "
          f"{outcome.wall_s:.1f} s), success {outcome.succeeded}/{n - outcome.crashed}"
          + (f", {outcome.crashed} crashed (the same command runs them again)"
             if outcome.crashed else "")
          + f"; {outcome.results}")  # fmt: skip
    report, cases = out / "report.md", out / "cases.jsonl"  # (appended to as each case ends)
    if report.exists() and cases.exists() and report.stat().st_mtime < cases.stat().st_mtime:
        print(f"{report} is older than these results: `sdh2svc campaign report {out}` writes "
              "it anew", file=sys.stderr)  # fmt: skip
    return Exit.FAILED if outcome.crashed else Exit.OK


@contextlib.contextmanager
def _sigterm_as_ctrl_c() -> Iterator[None]:
    """SIGTERM (`kill`) ends the block as Ctrl-C does (a campaign keeps its finished cases, an
    export the file as it was), and Ctrl-C is heard even where the shell had it ignored (a job
    started in the background): SIGTERM is sent on as SIGINT."""
    previous = signal.signal(signal.SIGTERM, _interrupt)
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        signal.signal(signal.SIGINT, previous_int)


def _interrupt(signum: int, frame: object) -> None:
    """SIGTERM as Ctrl-C: sent on as SIGINT, to SIGINT's own handler: while a campaign's case
    runs in this process that is asyncio's, which cancels the case's task. A KeyboardInterrupt
    raised here could land inside the event loop's own bookkeeping, and the loop then waited
    forever for a wake-up it had lost."""
    signal.raise_signal(signal.SIGINT)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sdh2svc", description="Tactile in-hand rolling on a SCHUNK SDH2 hand.",
        epilog=EXIT_STATUS_HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument("--version", action="version", version=f"sdh2svc {__version__}")
    parser.add_argument(
        "--debug", action="store_true",
        help="print the traceback of an unexpected error (or SDH2SVC_DEBUG=1)",
    )  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser(
        "config", help="print the effective configuration", description=cmd_config.__doc__
    )
    _add_config_args(p)
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("demo", help="the hand model at one pose", description=cmd_demo.__doc__)
    _add_config_args(p)
    for name, default in (("phi2", -20.0), ("phi3", 30.0), ("phi4", -20.0), ("phi5", 30.0)):
        p.add_argument(f"--{name}", type=float, default=default, help="deg (default %(default)s)")
    p.add_argument("--s1", type=float, default=20.0,
                   help="contact height S1 on Finger 1, mm (default %(default)s)")  # fmt: skip
    p.add_argument("--s2", type=float, default=20.0,
                   help="contact height S2 on Finger 2, mm (default %(default)s)")  # fmt: skip
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("sim", help="serve the simulated hand's two controllers",
                       description=cmd_sim.__doc__)  # fmt: skip
    _add_config_args(p)
    obj = p.add_mutually_exclusive_group()
    obj.add_argument("--object", help="a preset: rubber, egg, cylinder, stick62 … stick119")
    obj.add_argument("--object-file", metavar="FILE", help="an object defined in TOML or JSON")
    p.add_argument("--host", help="TCP bind address (default from config: 127.0.0.1)")
    p.add_argument("--dsa-port", type=_port_arg, help="DSACON32m TCP port (default 13000; 0 = any)")
    p.add_argument("--sdh-port", type=_port_arg, help="SDH2 TCP port (default 13023; 0 = any)")
    p.add_argument("--no-pty", action="store_true", help="serve on TCP only")
    p.add_argument("--no-tcp", action="store_true", help="serve on ptys only")
    p.add_argument("--baud", type=int, help="line pacing in bits/s (default 115200)")
    p.add_argument(
        "--boot-s",
        type=float,
        help="DSACON32m boot silence (8.0 = the real one), "
        "counted from the first host's connection: the controller powers up then",
    )
    p.add_argument("--ber", type=float, help="bit-error rate injected on device→host bytes")
    p.add_argument("--seed", type=int, help="random seed of the simulated world")
    p.add_argument("--replace-after", type=float, metavar="S",
                   help="put a released or dropped object back after S s untouched "
                        "(default 1; 0 = never)")  # fmt: skip
    press_help = (
        "press a pad: pad=0…5,x=MM,y=MM,force=N[,radius=MM][,duration=S][,at=S] "
        "(x across, y along from the fingertip's end, or a proximal pad's distal end; at: s "
        "after start; repeatable)"
    )
    p.add_argument("--press", action="append", type=_press_arg, metavar="SPEC", help=press_help)
    p.add_argument("--json", action="store_true", help="print the endpoints as one JSON line")
    p.set_defaults(func=cmd_sim)

    p = sub.add_parser("run", help="one rolling run (headless)", description=cmd_run.__doc__)
    _add_config_args(p)
    p.add_argument("--sim", action="store_true", help="on the embedded simulated hand")
    obj = p.add_mutually_exclusive_group()
    obj.add_argument("--object", help="simulated object preset (with --sim)")
    obj.add_argument("--object-file", metavar="FILE", help="simulated object file (with --sim)")
    p.add_argument("--cycles", type=_cycles_arg,
                   help="strokes before the run ends (rolling.cycles, 1 … 10000)")  # fmt: skip
    _add_link_args(p)
    p.add_argument("--fast", action="store_true",
                   help="virtual clock: as fast as the CPU allows (with --sim)")  # fmt: skip
    p.add_argument("--json", action="store_true", help="one JSON summary object on stdout")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("serve", help="the service: API, dashboard, 3-D view",
                       description=cmd_serve.__doc__)  # fmt: skip
    _add_config_args(p)
    p.add_argument("--sim", action="store_true", help="on the embedded simulated hand")
    obj = p.add_mutually_exclusive_group()
    obj.add_argument("--object", help="simulated object preset (with --sim)")
    obj.add_argument("--object-file", metavar="FILE", help="simulated object file (with --sim)")
    p.add_argument("--host", help="bind address (default 127.0.0.1; beyond loopback needs a "
                   "token: SDH2SVC_SERVICE__TOKEN)")  # fmt: skip
    p.add_argument("--port", type=_port_arg, help="HTTP port (default 8000; 0 = any free one)")
    p.add_argument("--viser-port", type=_port_arg, help="3-D view port (default 8080; 0 = any)")
    p.add_argument("--no-viewer", action="store_true", help="no viser 3-D view")
    _add_link_args(p)
    p.add_argument("--log-format", choices=["text", "json"], default="text",
                   help="log lines on stderr: text (journald) or json "
                        "(default %(default)s)")  # fmt: skip
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                   help="the lowest level logged (default %(default)s)")  # fmt: skip
    p.add_argument("--json", action="store_true", help="announce the URLs as one JSON line")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("health", help="is the service up? (exit status)",
                       description=cmd_health.__doc__)  # fmt: skip
    _add_config_args(p)
    p.add_argument("--url", help="the service's base URL http://HOST:PORT, or its /api/status "
                   "URL (default: from service.host/port)")  # fmt: skip
    p.add_argument("--timeout", type=_seconds_arg, default=4.0, metavar="S",
                   help="seconds to wait for the answer (> 0; default %(default)s)")  # fmt: skip
    p.set_defaults(func=cmd_health)

    p = sub.add_parser("runs", help="recorded runs: list, show, export, delete, prune, vacuum",
                       description=cmd_runs.__doc__)  # fmt: skip
    _add_config_args(p)
    p.add_argument("action", choices=["list", "show", "export", "delete", "prune", "vacuum"])
    p.add_argument(
        "id", nargs="*", default=[], type=_run_id, help="run ID (show, export; delete: one or more)"
    )
    p.add_argument("--keep", type=_count_arg, metavar="N",
                   help="prune: keep the newest N runs")  # fmt: skip
    p.add_argument("--before", type=_when_arg, metavar="WHEN",
                   help="prune: only runs started before WHEN: 30d or 12h ago, or a date (and "
                   "time) such as 2026-11-30")  # fmt: skip
    p.add_argument("--dry-run", action="store_true", help="delete, prune: say what would go")
    p.add_argument("--vacuum", action="store_true",
                   help="delete, prune: then shrink the file (as `runs vacuum`)")  # fmt: skip
    p.add_argument(
        "--format",
        choices=["csv", "mcap"],
        help="export format (default: the one --output's name ends in, else csv)",
    )
    p.add_argument(
        "--output",
        "-o",
        metavar="FILE",
        help="export file; - for stdout (default: stdout for CSV, run-ID.mcap for MCAP)",
    )
    p.set_defaults(func=cmd_runs, parser=p)  # (parse_args: IDs after an option, its usage)

    p = sub.add_parser("estop", help="the e-stop latch in the run database: show, latch, release",
                       description=cmd_estop.__doc__)  # fmt: skip
    _add_config_args(p)
    action = p.add_mutually_exclusive_group()
    action.add_argument("--latch", action="store_true", help="latch it (runs are refused)")
    action.add_argument("--release", action="store_true", help="release it")
    p.set_defaults(func=cmd_estop)

    p = sub.add_parser("campaign", help="campaigns: run a suite, report, compare, generate",
                       description=cmd_campaign.__doc__)  # fmt: skip
    _add_config_args(p)
    p.add_argument("action", choices=["run", "report", "compare", "generate"])
    p.add_argument("dir", metavar="SUITE|DIR",
                   help="run: a suite name (smoke, bench-v1, thesis) or a suite JSON file; "
                        "report: a campaign directory; compare: campaign A; generate: the new "
                        "suite's name")  # fmt: skip
    p.add_argument("dir_b", nargs="?", metavar="DIR_B", help="compare: campaign B")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, help="local worker processes (default: all CPUs)")
    where.add_argument("--ray", metavar="ADDRESS",
                       help="run on a Ray cluster: auto, ray://HOST:PORT, or local "
                            "(pip install 'sdh2svc[cluster]')")  # fmt: skip
    p.add_argument("--out", metavar="DIR", help="run: campaign directory (default "
                   "campaigns/SUITE_NAME); the same command again resumes there")  # fmt: skip
    p.add_argument("-o", "--output", metavar="FILE",
                   help="compare: markdown file (default DIR_B/compare.md); generate: the "
                        "suite file (default NAME.json)")  # fmt: skip
    p.add_argument("--seed", type=int, help="generate: the generator's seed")
    p.add_argument("--cases", type=int, help="generate: how many cases (families take turns)")
    p.add_argument("--quiet", action="store_true", help="run: no progress line")
    p.set_defaults(func=cmd_campaign)
    return parser


def parse_args(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """``parser.parse_args``, but run IDs may also follow an option (``runs delete --dry-run 3
    4``): argparse gives the IDs their (empty) share at the action already, and the rest would
    be refused as unrecognized arguments."""
    args, extra = parser.parse_known_args(argv)
    if extra and args.command == "runs" and not any(x.startswith("-") for x in extra):
        try:
            args.id = [*args.id, *(_run_id(x) for x in extra)]
        except argparse.ArgumentTypeError as e:
            args.parser.error(f"argument id: {e}")  # with runs's usage, as argparse's own
        extra = []
    if extra:
        # with the command's own usage (the top level's lists none of its options), and the
        # option it most resembles
        sub = _subparser(parser, getattr(args, "command", None)) or parser
        known = [o for a in sub._actions for o in a.option_strings]
        typed = next((x.split("=")[0] for x in extra if x.startswith("--")), "")
        near = difflib.get_close_matches(typed, known, n=1) if typed else []
        sub.error(f"unrecognized arguments: {' '.join(extra)}"
                  + (f" (did you mean {near[0]}?)" if near else ""))  # fmt: skip
    return args


def _subparser(parser: argparse.ArgumentParser, name: str | None) -> argparse.ArgumentParser | None:
    """The parser of command ``name``, if it has one."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            return action.choices[name]  # type: ignore[no-any-return]
    return None


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(build_parser(), argv)
    debug = _debug(args)
    try:
        status = int(args.func(args))
        if sys.stdout is not None:
            sys.stdout.flush()  # a full disk fails here, not in the exit's own flush
        return status
    except CliError as e:
        _report(args, e.message)
        return e.status
    except ConfigError as e:
        _report(args, str(e))
        return Exit.USAGE
    except KeyboardInterrupt:
        return Exit.INTERRUPTED
    except BrokenPipeError:  # the reader went away (`runs show 7 | head`): as `cat` does
        with contextlib.suppress(OSError):  # (the exit's own flush must not fail again)
            _quiet_stdout()
        return Exit.BROKEN_PIPE
    except Exception as e:
        if isinstance(e, OSError) and e.errno in _NO_ROOM:  # the output's disk, not a bug
            with contextlib.suppress(OSError):  # (the exit's own flush must not fail again)
                _quiet_stdout()
            what = e.filename or "its output"  # (stdout's failure names no file)
            _report(args, f"cannot write {what}: {e.strerror or e}")
            return Exit.UNAVAILABLE
        if debug:
            traceback.print_exc()
        hint = "" if debug else " (`sdh2svc --debug COMMAND …` prints the traceback)"
        _report(args, f"unexpected error (a bug): {type(e).__name__}: {_one_line(e)}{hint}")
        return Exit.BUG


# What a full or failing disk under the output says (`> /dev/full`, a full /tmp in a script)
_NO_ROOM = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO})


def _report(args: argparse.Namespace, message: str) -> None:
    """The failure on stderr, ``sdh2svc COMMAND: message`` (a log record under ``serve
    --log-format json``, so that the service's log stays one JSON object per line)."""
    if getattr(args, "log_format", None) == "json" and logging.getLogger().handlers:
        logging.getLogger("sdh2svc").error("%s", message)
    else:
        print(f"sdh2svc {args.command}: {message}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
