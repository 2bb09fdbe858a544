"""A small Zenoh client the netns tests run inside a network namespace (``ip netns exec NS python
tests/netns_probe.py ...``): the test process itself cannot reach a namespace's loopback.

``watch``: print one JSON line per message on the given keys, stamped with this machine's
monotonic clock (the same in every namespace), until killed.
``attack``: try to open a session (a TLS one with the given certificate, or none) and, if that
works, publish velocity commands and an e-stop clear and subscribe to the camera; print one JSON
line saying what happened.
``router``: a router as ``ovamos router`` runs it (:func:`ovamos.router.run_router`), told the
robots a fleet's laptop router binds (``--robot``, repeatable); ``--unchecked``: the same config
opened by Zenoh as written, without ovamos's start-up (no checks, no robots bound), which is what
a router did before, to reproduce what it let through.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh

from ovamos.shared import keys
from ovamos.shared.bus.zconfig import TlsFiles, build_config, open_session
from ovamos.shared.log import setup_logging
from ovamos.shared.messages import EStop, PlanCommand

_lock = threading.Lock()


def emit(**fields: object) -> None:
    with _lock:
        print(json.dumps({"t": time.monotonic(), **fields}), flush=True)


def watch(args: argparse.Namespace) -> None:
    session = zenoh.open(build_config("client", connect=[args.connect]))
    subs = []
    for name in args.keys.split(","):
        key = getattr(keys, name)(args.robot_id)

        def on_sample(sample: zenoh.Sample, name: str = name) -> None:
            try:
                emit(key=name, msg=json.loads(sample.payload.to_bytes()))
            except ValueError:
                emit(key=name, msg=None)
        subs.append(session.declare_subscriber(key, on_sample))
    emit(key="ready")
    threading.Event().wait()


def attack(args: argparse.Namespace) -> None:
    cfg = build_config("client", connect=[args.connect], require_certs=False)
    cfg.insert_json5("connect/timeout_ms", "3000")
    cfg.insert_json5("connect/exit_on_failure", "true")
    tls: dict[str, object] = {}
    if args.ca:
        tls.update(root_ca_certificate=args.ca, enable_mtls=True)
    if args.cert:
        tls.update(connect_certificate=args.cert, connect_private_key=args.key)
    if tls:
        cfg.insert_json5("transport/link/tls", json.dumps(tls))
    try:
        session = zenoh.open(cfg)
    except zenoh.ZError as exc:
        emit(opened=False, error=str(exc)[:300])
        return
    frames = []
    sub = session.declare_subscriber(keys.rgbd(args.robot_id), lambda s: frames.append(1))
    time.sleep(0.5)
    for i in range(10):
        session.put(keys.plan_command(args.robot_id),
                    bytes(PlanCommand(action_id=10**6 + i, stamp=time.time(), linear=0.2).to_bytes()))
        for key in (keys.estop(args.robot_id), keys.estop_clear(args.robot_id)):
            session.put(key, bytes(EStop(engage=False, source="intruder", stamp=time.time()).to_bytes()))
        time.sleep(0.1)
    time.sleep(1.0)
    sub.undeclare()
    session.close()
    emit(opened=True, frames=len(frames))


def router(args: argparse.Namespace) -> None:
    from ovamos.router import run_router
    setup_logging()
    cfg = build_config("router", file=args.config, listen=args.listen, connect=args.connect,
                       tls=TlsFiles.from_folder(args.certs, args.cert), require_certs=not args.unchecked)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.unchecked:
        session = open_session(cfg)
        stop.wait()
        session.close()
        return
    run_router(cfg, robot_id=args.robot_id, robots=args.robot, name=args.cert, stop=stop)


def main() -> None:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="mode", required=True)
    w = sub.add_parser("watch")
    w.add_argument("--connect", required=True)
    w.add_argument("--robot-id", default="robot1")
    w.add_argument("--keys", default="odom,driver_state")
    a = sub.add_parser("attack")
    a.add_argument("--connect", required=True)
    a.add_argument("--robot-id", default="robot1")
    a.add_argument("--ca")
    a.add_argument("--cert")
    a.add_argument("--key")
    r = sub.add_parser("router")
    r.add_argument("--config", required=True)
    r.add_argument("--certs", required=True)
    r.add_argument("--cert", required=True)
    r.add_argument("--listen", action="append", default=[])
    r.add_argument("--connect", action="append", default=[])
    r.add_argument("--robot-id", default="robot1")
    r.add_argument("--robot", action="append", default=[])
    r.add_argument("--unchecked", action="store_true")
    args = parser.parse_args()
    {"watch": watch, "attack": attack, "router": router}[args.mode](args)


if __name__ == "__main__":
    main()
