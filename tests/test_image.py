"""The container image, built and run here with podman (no Docker engine, no registry): a Debian
base made with debootstrap and the local CPU torch wheel. A client on the host opens a session,
streams a short trajectory and receives estimates; the health check asks the service's info key;
SIGTERM stops the container within 5 s."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from service_process import free_port

from inhand_tracker.client import TrackerClient
from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.paths import DATA_DIR

ROOT = Path(__file__).resolve().parents[1]
TAG = "localhost/inhand-tracker:test"
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("podman") is None or shutil.which("debootstrap") is None,
                       reason="needs podman and debootstrap (apt-get install podman buildah runc debootstrap)"),
]  # fmt: skip


def _podman(*args: str, timeout: float = 120, check: bool = True) -> subprocess.CompletedProcess:
    env = os.environ | {"CONTAINERS_CONF": str(Path.home() / ".cache/inhand-tracker/podman/containers.conf")}
    return subprocess.run(["podman", *args], capture_output=True, text=True, timeout=timeout, check=check, env=env)


def test_the_image_serves_a_client_on_the_host_and_stops_on_sigterm(tmp_path, capsys):
    build = subprocess.run([str(ROOT / "docker/build-local.sh"), TAG], capture_output=True, text=True, timeout=3000)
    assert build.returncode == 0, (build.stdout + build.stderr)[-4000:]
    figures = [line for line in build.stdout.splitlines() if line.startswith(("build time", "image size"))]
    with capsys.disabled():  # shown in CI's log whatever pytest captures
        print("\n" + "; ".join(figures))

    port = free_port()
    cache = tmp_path / "warp-cache"  # the host's compiled kernels, so the container need not compile them again
    host_cache = Path.home() / ".cache/warp"
    if host_cache.exists():
        shutil.copytree(host_cache, cache)
    cache.mkdir(exist_ok=True)
    subprocess.run(["chmod", "-R", "a+rwX", str(cache)], check=True)
    name = f"inhand-test-{port}"
    # No frame budget: on a busy CI machine the CPU's step times could refuse the open.
    env = [f"INHAND_LISTEN=tcp/127.0.0.1:{port}", "INHAND_DEVICE=cpu", "INHAND_GROUPS=1", "INHAND_RATE_HZ=0"]
    volume = f"{cache}:/home/tracker/.cache/warp"
    _podman("run", "-d", "--name", name, "--network", "host", *(f"--env={e}" for e in env), "-v", volume, TAG)
    try:
        traj = Trajectory.load(DATA_DIR / "smoke-foam_brick_pick_place_0.traj")
        with TrackerClient(connect=[f"tcp/127.0.0.1:{port}"]) as client:
            try:  # it answers while it warms up, and is ready (and healthy) once its kernels are compiled
                info = client.wait_ready(timeout=300)
            except TimeoutError:
                pytest.fail(_podman("logs", name, check=False).stdout[-3000:])
            assert info.device == "cpu" and "foam_brick" in info.objects
            health = _podman("healthcheck", "run", name, check=False)
            assert health.returncode == 0, health.stdout + health.stderr
            session = client.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q)
            for i in range(20):
                client.send(traj.frame(i, session.session))
                estimate = client.latest_pose(timeout=120, after_seq=i)
            assert estimate.seq == 19 and estimate.pose.shape == (7,)
            client.close_session()
        t0 = time.monotonic()
        _podman("kill", "--signal", "TERM", name)
        code = _podman("wait", name, timeout=30).stdout.strip()
        took = time.monotonic() - t0
        with capsys.disabled():
            print(f"SIGTERM to exit: {took:.2f} s, exit code {code}")
        assert code == "0" and took < 5.0, (code, took, _podman("logs", name, check=False).stdout[-2000:])
    finally:
        _podman("rm", "-f", name, check=False)
