"""The package as users install it, in fresh virtual environments: `pip install .` gives the robot
side (no torch), whose command says what to install for the rest; `pip install .[service]` gives a
service that runs the demo from any directory (configs and data travel inside the package)."""

from __future__ import annotations

import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_NOT_SOURCE = (".git", ".venv", ".gpu", ".before", "bench-results", "build", "dist", "*.egg-info", "__pycache__")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The project's wheel, built from a copy of the tree (a build writes into its source)."""
    tmp = tmp_path_factory.mktemp("build")
    src = shutil.copytree(ROOT, tmp / "src", ignore=shutil.ignore_patterns(*_NOT_SOURCE))
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", str(src), "-w", str(tmp)],
        check=True, timeout=300,
    )  # fmt: skip
    (path,) = tmp.glob("inhand_tracker-*.whl")
    return path


@pytest.mark.slow
def test_the_wheel_installs_one_top_level_package_with_every_subpackage(wheel):
    """``inhand_tracker`` alone at the top of site-packages: nothing to collide with a workspace's
    own ``client`` or ``service``; and every source folder with a module travels inside it."""
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names if ".dist-info/" not in n} == {"inhand_tracker"}
    folders = {p.parent for d in ("client", "protocol", "service", "sim_backend") for p in (ROOT / d).rglob("*.py")}
    missing = [f for f in folders if f"inhand_tracker/{f.relative_to(ROOT)}/__init__.py" not in names]
    assert not missing, missing


def _venv(path: Path) -> Path:
    subprocess.run([sys.executable, "-m", "venv", str(path)], check=True, timeout=300)
    return path / "bin"


def _run(bin_: Path, *args: str, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([str(bin_ / args[0]), *args[1:]], cwd=cwd, capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
def test_the_base_install_is_the_robot_side_without_torch(wheel, tmp_path):
    bin_ = _venv(tmp_path / "robot")
    out = _run(bin_, "pip", "install", "-q", str(wheel), cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert _run(bin_, "python", "-c", "import torch", cwd=tmp_path).returncode != 0  # nothing pulled it in
    version = _run(bin_, "inhand-tracker", "--version", cwd=tmp_path)
    assert version.returncode == 0 and version.stdout.startswith("inhand-tracker 0."), version.stderr
    for command in (("replay", "--help"), ("watch", "--help"), ("spec", "--out", str(tmp_path / "spec"))):
        out = _run(bin_, "inhand-tracker", *command, cwd=tmp_path)
        assert out.returncode == 0, (command, out.stderr[-2000:])
    assert (tmp_path / "spec" / "golden" / "Estimate.msgpack").exists()
    out = _run(bin_, "inhand-tracker", "serve", cwd=tmp_path)
    assert out.returncode == 2 and "pip install '.[service]' in the repository" in out.stderr, out.stderr[-2000:]


@pytest.mark.slow
def test_the_service_install_runs_the_demo_from_another_directory(wheel, tmp_path):
    bin_ = _venv(tmp_path / "service")
    # The service's dependencies are this environment's (torch, warp, newton: GBs to fetch again);
    # the project itself is installed from its wheel, extras resolved against them.
    (purelib,) = (tmp_path / "service" / "lib").glob("python3*/site-packages")
    (purelib / "deps.pth").write_text(site.getsitepackages()[0] + "\n")
    out = _run(bin_, "pip", "install", "-q", f"{wheel}[service]", cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    where = _run(bin_, "python", "-c", "import inhand_tracker.service.paths as p; print(p.PROJECT_ROOT)", cwd=tmp_path)
    assert str(purelib) in where.stdout, where  # the installed copy, not this checkout
    out = _run(bin_, "inhand-tracker", "demo", "--device", "cpu", "--worlds", "4", cwd=tmp_path, timeout=1800)
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-3000:])
    assert "estimates: " in out.stdout and "position error" in out.stdout, out.stdout[-2000:]
