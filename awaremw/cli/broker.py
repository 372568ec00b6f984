"""``awaremw broker --mosquitto [--port P]``: Mosquitto with ``broker_cfg/``, outside Docker.

``broker_cfg/mosquitto.conf`` names the paths of the eclipse-mosquitto
container (``/mosquitto/config/passwd``...). This verb copies the password file
and the ACL into a work directory, rewrites the configuration to those local
paths and the chosen listener, and runs ``mosquitto`` in the foreground until
Ctrl-C. The accounts are those of ``broker_cfg/passwd``: ``operator`` (writes
definitions and commands), ``gateway`` (the awaremw gateway: writes data,
groups, status, errors), ``viewer`` (reads); the committed file holds the test
passwords ``<name>-pw`` -- regenerate it with ``broker_cfg/make_passwd.sh`` for
anything shared.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import FrameType

from awaremw.cli.friendly import refuse
from awaremw.cli.helptext import add_log_format, add_verb

READY_TIMEOUT_S = 10.0


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = add_verb(
        subparsers,
        "broker",
        "run Mosquitto with broker_cfg/ (accounts, ACL) here",
        """\
Mosquitto with broker_cfg/, outside Docker: the password file and the ACL are
copied into a work directory, the configuration rewritten to those local paths
and the chosen listener, and mosquitto runs in the foreground until Ctrl-C.
Accounts of broker_cfg/passwd: operator (definitions and commands), gateway
(data, groups, status, errors), viewer (reads); the committed file holds the
test passwords <name>-pw (broker_cfg/make_passwd.sh makes real ones).""",
        ["awaremw broker --mosquitto --port 1884"],
    )
    p.add_argument(
        "--mosquitto",
        action="store_true",
        required=True,
        help="run the mosquitto binary (the only broker this verb runs; the embedded one "
        "comes with awaremw gateway and awaremw demo)",
    )
    p.add_argument("--port", type=int, default=1883, help="listener port (default 1883)")
    p.add_argument("--host", default="127.0.0.1", help="listener address (default 127.0.0.1)")
    p.add_argument(
        "--config",
        default=None,
        metavar="DIR",
        help="directory with mosquitto.conf, passwd, acl (default: ./broker_cfg, else the "
        "repository's broker_cfg/)",
    )
    p.add_argument(
        "--workdir",
        default=None,
        metavar="DIR",
        help="where the rewritten configuration, the copies and the log go; persistence "
        "(retained definitions across restarts) is on only with it (default: a temporary "
        "directory, persistence off)",
    )
    add_log_format(p)
    p.set_defaults(func=run)


def find_config(explicit: str | None) -> Path:
    """The ``broker_cfg`` directory to use; raises FileNotFoundError with the places tried."""
    here = Path(__file__).resolve().parents[2] / "broker_cfg"  # a clone / editable install
    tried = [Path(explicit)] if explicit is not None else [Path("broker_cfg"), here]
    for d in tried:
        if (d / "mosquitto.conf").is_file():
            return d.resolve()
    raise FileNotFoundError(
        "no mosquitto.conf in " + " or ".join(str(d) for d in tried) + " (give --config DIR)"
    )


def local_config(
    cfg: Path,
    workdir: Path,
    port: int,
    *,
    host: str = "127.0.0.1",
    persistence: bool = False,
    extra: tuple[str, ...] = (),
) -> Path:
    """Write ``workdir/mosquitto.conf``: ``cfg``'s, with local paths and one listener.

    ``passwd`` and ``acl`` are copied into ``workdir`` (the broker reads the
    copies; edit them there to lock accounts out). The log goes to
    ``workdir/mosquitto.log``. Returns the configuration's path.
    """
    workdir.mkdir(parents=True, exist_ok=True)
    passwd, acl = workdir / "passwd", workdir / "acl"
    shutil.copy(cfg / "passwd", passwd)
    shutil.copy(cfg / "acl", acl)
    passwd.chmod(0o600)  # recent Mosquitto warns about (and will refuse) readable password files
    lines = []
    listeners = 0
    for line in (cfg / "mosquitto.conf").read_text(encoding="utf-8").splitlines():
        key = line.split(" ", 1)[0]
        if key == "password_file":
            line = f"password_file {passwd}"
        elif key == "acl_file":
            line = f"acl_file {acl}"
        elif key == "listener":
            listeners += 1
            if listeners > 1:  # the TLS listener needs certificates: pass it in ``extra``
                continue
            line = f"listener {port} {host}"
        elif key in ("certfile", "keyfile", "cafile"):
            continue
        elif key == "persistence":
            line = f"persistence {'true' if persistence else 'false'}"
        elif key == "persistence_location":
            if not persistence:
                continue
            line = f"persistence_location {workdir}/"
        elif key == "log_dest":
            continue
        lines.append(line)
    lines.append(f"log_dest file {workdir / 'mosquitto.log'}")
    lines.extend(extra)
    if os.geteuid() == 0:
        lines.append("user root")  # else mosquitto drops to a user that cannot read workdir
    conf = workdir / "mosquitto.conf"
    conf.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return conf


def find_mosquitto() -> str | None:
    found = shutil.which("mosquitto")
    if found:
        return found
    for d in ("/usr/sbin", "/usr/local/sbin"):
        if os.access(f"{d}/mosquitto", os.X_OK):
            return f"{d}/mosquitto"
    return None


def wait_listening(proc: subprocess.Popen[bytes], host: str, port: int, timeout: float) -> str:
    """Poll the port until it accepts (Mosquitto gives no readiness signal); '' or why not."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return f"mosquitto exited with status {proc.returncode}"
        with (
            contextlib.suppress(OSError),
            socket.create_connection((host, port), timeout=0.2),
        ):
            return ""
        time.sleep(0.05)
    return f"mosquitto did not listen on {host}:{port} within {timeout:g} s"


def run(args: argparse.Namespace) -> int:
    binary = find_mosquitto()
    if binary is None:
        return refuse("awaremw broker", "mosquitto not found (Debian: apt-get install mosquitto)")
    if not 0 < args.port < 65536:
        return refuse("awaremw broker", "--port must be in 1..65535")
    try:
        cfg = find_config(args.config)
    except FileNotFoundError as e:
        return refuse("awaremw broker", e)
    with contextlib.ExitStack() as stack:
        if args.workdir is None:
            workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="awaremw-mq-")))
        else:
            workdir = Path(args.workdir).resolve()
        conf = local_config(
            cfg, workdir, args.port, host=args.host, persistence=args.workdir is not None
        )
        log_file = workdir / "mosquitto.log"
        proc = subprocess.Popen([binary, "-c", str(conf)], stdout=subprocess.DEVNULL)
        stop = False

        def on_signal(signum: int, frame: FrameType | None) -> None:
            nonlocal stop
            stop = True
            if proc.poll() is None:
                proc.terminate()

        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
        why = wait_listening(proc, args.host, args.port, READY_TIMEOUT_S)
        if why and not stop:
            if proc.poll() is None:
                proc.terminate()
                proc.wait(5)
            tail = log_file.read_text(errors="replace").strip().splitlines()[-1:] if (
                log_file.exists()
            ) else []  # fmt: skip
            print(f"awaremw broker: {why}" + (f": {tail[0]}" if tail else ""), file=sys.stderr)
            return 1
        where = f"{args.host}:{args.port}"
        print(
            f"awaremw broker: Mosquitto on mqtt://{where} with {cfg}/ (accounts operator, "
            f"gateway, viewer; ACL {cfg}/acl); log {log_file}",
            flush=True,
        )
        print(
            f"awaremw broker: gateway: --mqtt mqtt://gateway:PASSWORD@{where}; definitions "
            f"and the robot: mqtt://operator:PASSWORD@{where}",
            flush=True,
        )
        code = proc.wait()
        return 0 if stop else (code or 1)
