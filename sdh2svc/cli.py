"""The ``sdh2svc`` command line."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence

from sdh2svc import __version__
from sdh2svc.config import ConfigError, Settings, load_config
from sdh2svc.model.friction import inside_cone, omega
from sdh2svc.model.geometry import pad_point_from_L, virtual_joint
from sdh2svc.model.kinematics import Finger, HandPose, hand_points, segment


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="a TOML file overriding config/default.toml")
    p.add_argument(
        "--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
        help="override one key, e.g. --set rolling.k=3 (repeatable; beats file and environment)",
    )  # fmt: skip


def _load(args: argparse.Namespace) -> Settings:
    return load_config(args.config, args.overrides)


def cmd_config(args: argparse.Namespace) -> int:
    """Print the effective, validated configuration as JSON."""
    print(json.dumps(_load(args).model_dump(mode="json"), indent=2, ensure_ascii=False))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """The hand model at one pose: contact points, object segment and friction cones."""
    cfg = _load(args)
    pad = cfg.hand.pad
    s_range = (cfg.tactile.distal.rows - 1) * cfg.tactile.texel_pitch_mm
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
    TCP ports, for any driver — ours, SCHUNK's SDHLibrary, the ROS node — until Ctrl-C."""
    import asyncio
    import signal

    from sdh2svc.sim.objects import get_object, load_object
    from sdh2svc.sim.serve import start_simulated_hand

    overrides = list(args.overrides)
    for flag, key in (("host", "host"), ("boot_s", "dsa_boot_s"), ("ber", "bit_error_rate"),
                      ("baud", "baud")):  # fmt: skip
        if getattr(args, flag) is not None:
            overrides.append(f"sim.links.{key}={getattr(args, flag)!r}")
    if args.seed is not None:
        overrides.append(f"sim.seed={args.seed}")
    if args.replace_after is not None:
        overrides.append(f"sim.replace_after_s={args.replace_after!r}")
    cfg = load_config(args.config, overrides)
    try:
        obj = (
            load_object(args.object_file)
            if args.object_file
            else get_object(args.object or cfg.sim.object)
        )
    except (KeyError, OSError, ValueError) as e:
        print(f"sdh2svc sim: {e}", file=sys.stderr)
        return 2

    async def main() -> None:
        hand = await start_simulated_hand(
            cfg, obj=obj, pty=not args.no_pty and cfg.sim.links.pty, tcp=not args.no_tcp,
            dsa_port=args.dsa_port, sdh_port=args.sdh_port,
        )  # fmt: skip
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        info = {"object": obj.name or obj.kind, "dsa": hand.urls("dsa"), "sdh": hand.urls("sdh")}
        if args.json:
            print(json.dumps(info), flush=True)
        else:
            print(f"sdh2svc sim: a simulated SCHUNK SDH2; object "
                  f"{info['object']!r} ({obj.kind}, {obj.size_mm:g} mm) waits between the "
                  f"fingertips")  # fmt: skip
            print(f"  DSACON32m (tactile): {'   '.join(info['dsa'])}")
            print(f"  SDH2 (joints):       {'   '.join(info['sdh'])}")
            print("  Point a driver at one URL of each. Ctrl-C stops.", flush=True)
        try:
            await stop.wait()
        finally:
            await hand.stop()

    asyncio.run(main())
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """One rolling run: pre-shape, grasp, roll for N strokes, release — on the simulated hand
    (--sim) or a real one (--dsa/--sdh or the config's links). Exit status 0 only if completed."""
    import asyncio

    from sdh2svc.control.runner import Runner
    from sdh2svc.service.headless import run_once
    from sdh2svc.sim.objects import get_object, load_object

    overrides = list(args.overrides)
    if args.cycles is not None:
        overrides.append(f"rolling.cycles={args.cycles}")
    cfg = load_config(args.config, overrides)
    obj = None
    if args.sim:
        try:
            obj = (
                load_object(args.object_file)
                if args.object_file
                else get_object(args.object or cfg.sim.object)
            )
        except (KeyError, OSError, ValueError) as e:
            print(f"sdh2svc run: {e}", file=sys.stderr)
            return 2
    elif args.object or args.object_file or args.fast:
        print("sdh2svc run: --object, --object-file and --fast need --sim", file=sys.stderr)
        return 2

    def progress(r: Runner) -> None:
        if args.json or not sys.stderr.isatty():
            return
        F = r.result.forces[-1] if r.result.forces else 0.0
        sig = r.result.sigmas[-1] if r.result.sigmas else 0.0
        print(f"\r{r.phase.value:10s} stroke {r.state.strokes} of {r.params.cycles}  "
              f"iteration {r.state.iteration:5d}  F {F:5.2f}  σ {sig:6.2f}°", end="",
              file=sys.stderr)  # fmt: skip

    if args.fast:
        from sdh2svc.sim.clock import run_fast

        summary = run_fast(run_once(cfg, sim=True, obj=obj, fast=True, progress=progress))
    else:
        summary = asyncio.run(run_once(cfg, sim=args.sim, obj=obj, dsa_url=args.dsa,
                                       sdh_url=args.sdh, progress=progress))  # fmt: skip
    if args.json:
        print(json.dumps(summary))
    else:
        print(file=sys.stderr)
        f = summary["force"]
        print(f"run {summary['run_id']}: {summary['status']} {summary['message']}".rstrip())
        print(
            f"  strokes {summary['strokes']}, iterations {summary['iterations']}, "
            f"reversals {len(summary['reversals'])}, Λ at grasp {summary['lambda_initial_mm']}"
        )
        if f["mean"] is not None:
            print(
                f"  F mean {f['mean']:.2f} (sd {f['sd'] or 0:.2f}, {f['min']:.2f}…{f['max']:.2f})"
                f", loop {summary['loop_hz'] or 0:.1f} Hz"
            )
        if "truth" in summary:
            print(f"  simulation truth: {summary['truth']}")
    return 0 if summary["status"] == "completed" else 1


def cmd_serve(args: argparse.Namespace) -> int:
    """The service: REST/WebSocket API, dashboard and 3-D view, on the embedded simulated hand
    (--sim) or a real one (--dsa/--sdh or the config's links). Ctrl-C/SIGTERM stop motion first."""
    import asyncio

    from sdh2svc.service.serve import ExposureError, serve, setup_logging
    from sdh2svc.sim.objects import get_object, load_object

    overrides = list(args.overrides)
    for key, value in (("host", args.host), ("port", args.port), ("viser_port", args.viser_port)):
        if value is not None:
            overrides.append(f"service.{key}={json.dumps(value)}")
    if args.no_viewer:
        overrides.append("service.viewer=false")
    cfg = load_config(args.config, overrides)
    setup_logging(args.log_format, args.log_level)
    obj = None
    if args.object or args.object_file:
        if not args.sim:
            print("sdh2svc serve: --object and --object-file need --sim", file=sys.stderr)
            return 2
        try:
            obj = load_object(args.object_file) if args.object_file else get_object(args.object)
        except (KeyError, OSError, ValueError) as e:
            print(f"sdh2svc serve: {e}", file=sys.stderr)
            return 2
    try:
        return asyncio.run(serve(cfg, sim=args.sim, dsa_url=args.dsa, sdh_url=args.sdh, obj=obj,
                                 announce_json=args.json))  # fmt: skip
    except ExposureError as e:
        print(f"sdh2svc serve: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def cmd_health(args: argparse.Namespace) -> int:
    """Exit 0 if the service answers GET /api/status with both links connected (HEALTHCHECK)."""
    import urllib.error
    import urllib.request

    cfg = _load(args)
    host = cfg.service.host if cfg.service.host not in ("0.0.0.0", "::") else "127.0.0.1"
    url = args.url or f"http://{host}:{cfg.service.port}/api/status"
    try:
        with urllib.request.urlopen(url, timeout=args.timeout) as r:
            status = json.load(r)
    except (OSError, ValueError, urllib.error.URLError) as e:
        print(f"sdh2svc health: {url}: {e}", file=sys.stderr)
        return 1
    down = [name for name, up in status["hand"]["connected"].items() if not up]
    if down:
        print(f"sdh2svc health: link(s) down: {', '.join(down)}", file=sys.stderr)
        return 1
    print(f"ok: {url}")
    return 0


def cmd_runs(args: argparse.Namespace) -> int:
    """Recorded runs: list them, show one, export one as CSV or MCAP."""
    from sdh2svc.service.store import RunStore

    cfg = load_config(args.config, args.overrides)
    store = RunStore(cfg.storage.db_path)
    try:
        if args.action == "list":
            for r in store.runs():
                print(f"{r['id']:5d}  {r['started_at']}  {r['status']:10s}  "
                      f"{r['iterations']:6d} iterations")  # fmt: skip
            return 0
        if args.id is None:
            print(f"sdh2svc runs {args.action}: which run? (give its ID)", file=sys.stderr)
            return 2
        run = store.run(args.id)
        if run is None:
            print(f"sdh2svc runs: no run {args.id} in {cfg.storage.db_path}", file=sys.stderr)
            return 2
        if args.action == "show":
            print(json.dumps(run, indent=2, ensure_ascii=False))
        elif args.format == "csv":
            out = open(args.output, "w", newline="") if args.output else sys.stdout  # noqa: SIM115
            try:
                store.export_csv(args.id, out)
            finally:
                if args.output:
                    out.close()
        else:
            path = args.output or f"run-{args.id}.mcap"
            with open(path, "wb") as fh:
                n = store.export_mcap(args.id, fh)
            print(f"{path}: {n} messages", file=sys.stderr)
        return 0
    finally:
        store.close()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sdh2svc", description="Tactile in-hand rolling on a SCHUNK SDH2 hand."
    )
    parser.add_argument("--version", action="version", version=f"sdh2svc {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser(
        "config", help="print the effective configuration", description=cmd_config.__doc__
    )
    _add_config_args(p)
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("demo", help="the hand model at one pose", description=cmd_demo.__doc__)
    _add_config_args(p)
    for name, default in (("phi2", -20.0), ("phi3", 30.0), ("phi4", -20.0), ("phi5", 30.0)):
        p.add_argument(f"--{name}", type=float, default=default, help=f"deg (default {default})")
    p.add_argument("--s1", type=float, default=20.0, help="contact height S1 on Finger 1, mm")
    p.add_argument("--s2", type=float, default=20.0, help="contact height S2 on Finger 2, mm")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("sim", help="serve the simulated hand's two controllers",
                       description=cmd_sim.__doc__)  # fmt: skip
    _add_config_args(p)
    obj = p.add_mutually_exclusive_group()
    obj.add_argument("--object", help="a preset: rubber, egg, cylinder, stick62 … stick119")
    obj.add_argument("--object-file", metavar="FILE", help="an object defined in TOML or JSON")
    p.add_argument("--host", help="TCP bind address (default from config: 127.0.0.1)")
    p.add_argument("--dsa-port", type=int, help="DSACON32m TCP port (default 13000; 0 = any)")
    p.add_argument("--sdh-port", type=int, help="SDH2 TCP port (default 13023; 0 = any)")
    p.add_argument("--no-pty", action="store_true", help="serve on TCP only")
    p.add_argument("--no-tcp", action="store_true", help="serve on ptys only")
    p.add_argument("--baud", type=int, help="line pacing in bits/s (default 115200)")
    p.add_argument("--boot-s", type=float, help="DSACON32m boot silence (8.0 = the real one)")
    p.add_argument("--ber", type=float, help="bit-error rate injected on device→host bytes")
    p.add_argument("--seed", type=int, help="random seed of the simulated world")
    p.add_argument("--replace-after", type=float, metavar="S",
                   help="put a released or dropped object back after S s untouched "
                        "(default 1; 0 = never)")  # fmt: skip
    p.add_argument("--json", action="store_true", help="print the endpoints as one JSON line")
    p.set_defaults(func=cmd_sim)

    p = sub.add_parser("run", help="one rolling run (headless)", description=cmd_run.__doc__)
    _add_config_args(p)
    p.add_argument("--sim", action="store_true", help="on the embedded simulated hand")
    obj = p.add_mutually_exclusive_group()
    obj.add_argument("--object", help="simulated object preset (with --sim)")
    obj.add_argument("--object-file", metavar="FILE", help="simulated object file (with --sim)")
    p.add_argument("--cycles", type=int, help="strokes before the run ends (rolling.cycles)")
    p.add_argument("--dsa", metavar="URL", help="DSACON32m port or pyserial URL (real hand)")
    p.add_argument("--sdh", metavar="URL", help="SDH2 port or pyserial URL (real hand)")
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
    p.add_argument("--port", type=int, help="HTTP port (default 8000; 0 = any free one)")
    p.add_argument("--viser-port", type=int, help="3-D view port (default 8080; 0 = any)")
    p.add_argument("--no-viewer", action="store_true", help="no viser 3-D view")
    p.add_argument("--dsa", metavar="URL", help="DSACON32m port or pyserial URL (real hand)")
    p.add_argument("--sdh", metavar="URL", help="SDH2 port or pyserial URL (real hand)")
    p.add_argument("--log-format", choices=["text", "json"], default="text",
                   help="log lines on stderr: text (journald) or json")  # fmt: skip
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    p.add_argument("--json", action="store_true", help="announce the URLs as one JSON line")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("health", help="is the service up? (exit status)",
                       description=cmd_health.__doc__)  # fmt: skip
    _add_config_args(p)
    p.add_argument("--url", help="status URL (default: from service.host/port)")
    p.add_argument("--timeout", type=float, default=4.0, help="seconds")
    p.set_defaults(func=cmd_health)

    p = sub.add_parser("runs", help="recorded runs: list, show, export",
                       description=cmd_runs.__doc__)  # fmt: skip
    _add_config_args(p)
    p.add_argument("action", choices=["list", "show", "export"])
    p.add_argument("id", nargs="?", type=int, help="run ID (show, export)")
    p.add_argument("--format", choices=["csv", "mcap"], default="csv", help="export format")
    p.add_argument(
        "--output", "-o", metavar="FILE", help="export file (default: stdout / run-ID.mcap)"
    )
    p.set_defaults(func=cmd_runs)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except ConfigError as e:
        print(f"sdh2svc: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
