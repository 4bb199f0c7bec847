"""`inhand-tracker serve` in a subprocess on a free loopback port, for the tests that talk to it
over real Zenoh."""

from __future__ import annotations

import contextlib
import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from inhand_tracker.client import TrackerClient, TrackerError

ROOT = Path(__file__).resolve().parents[1]


_GIVEN: set[int] = set()


def free_port() -> int:
    """A loopback port nothing listens on, below the kernel's ephemeral range: a port the kernel
    picks for ``bind(0)`` comes from that range, where it can be handed to another test's outgoing
    connection before the service listens on it ("the address is taken")."""
    low = 32768
    with contextlib.suppress(OSError, ValueError):
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    for _ in range(200):
        port = rng.randrange(max(1024, low - 12000), low)
        if port in _GIVEN:
            continue
        with socket.socket() as s, contextlib.suppress(OSError):
            s.bind(("127.0.0.1", port))
            _GIVEN.add(port)
            return port
    raise RuntimeError(f"no free loopback port below {low}")


class ServiceProcess:
    """`inhand-tracker serve` in a subprocess on a free loopback port."""

    def __init__(
        self,
        port: int,
        groups: int = 1,
        timeout_s: float = 1.0,
        scheme: str = "tcp",
        listen: bool = True,
        **settings: str,
    ):
        """``listen``: on the port; else on nothing (a client of a router named by ``settings``)."""
        self.endpoint = f"{scheme}/127.0.0.1:{port}"
        # No frame budget unless a test sets one: a busy CI machine's timings must not refuse opens.
        env = os.environ | {"INHAND_GROUPS": str(groups), "INHAND_ROBOT_TIMEOUT_S": str(timeout_s)}
        env |= {"INHAND_RATE_HZ": "0"}
        env |= {f"INHAND_{k.upper()}": v for k, v in settings.items()}
        endpoints = ["--listen", self.endpoint] if listen else []
        if not listen:
            env["INHAND_LISTEN"] = ""
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "inhand_tracker.service.cli", "serve", *endpoints, "--device", "cpu"],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            # A write past a file-size limit (:meth:`limit_files`) fails instead of killing it.
            preexec_fn=lambda: signal.signal(signal.SIGXFSZ, signal.SIG_IGN),
        )  # fmt: skip

    def wait_ready(self, client: TrackerClient, timeout: float = 900.0) -> None:
        # A first start on a cold kernel cache compiles for minutes before the service is ready.
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, self.proc.stdout.read()[-3000:]
            try:
                if client.service_info(timeout=1.0).ready:
                    return
                time.sleep(0.2)
            except (TimeoutError, TrackerError):
                time.sleep(0.2)
        raise TimeoutError("service did not come up")

    def limit_files(self, size: int) -> None:
        """From now on no file of the process may grow past ``size`` bytes: the kernel refuses the
        write (EFBIG), as a full disk does (ENOSPC)."""
        import resource

        resource.prlimit(self.proc.pid, resource.RLIMIT_FSIZE, (size, size))

    def stop(self) -> float:
        """SIGTERM; returns how long it took to exit."""
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout=30)
        return time.monotonic() - t0
