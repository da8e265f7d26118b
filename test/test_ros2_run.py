"""The `ros2 run genreg_ros register_node` contract, without the ros2 CLI (not installable here).

The package is built and installed with colcon into a temporary prefix; the environment comes from the
prefix's own setup script (as a user's shell gets it); the executable is resolved as `ros2 run` does:
the package prefix from the ament index (AMENT_PREFIX_PATH entries holding
share/ament_index/resource_index/packages/genreg_ros), then the executable file lib/genreg_ros/register_node.
It is run with the installed params file, must publish diagnostics, and must exit cleanly on SIGINT.
"""

from __future__ import annotations

import ast
import os
import py_compile
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray

REPO = Path(__file__).resolve().parent.parent
PKG, EXE = "genreg_ros", "register_node"


@pytest.fixture(scope="module")
def install_prefix(tmp_path_factory) -> Path:
    """colcon build --merge-install of this repository into a temporary prefix."""
    colcon = shutil.which("colcon")
    assert colcon, "colcon (colcon-common-extensions) is required"
    base = tmp_path_factory.mktemp("colcon")
    cmd = [colcon, "--log-base", str(base / "log"), "build", "--base-paths", str(REPO),
           "--build-base", str(base / "build"), "--install-base", str(base / "install"),
           "--merge-install", "--packages-select", PKG]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=base, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return base / "install"


def sourced_env(prefix: Path) -> dict[str, str]:
    """The environment after `. <prefix>/local_setup.sh` (what a user's shell has after sourcing it)."""
    env = {k: v for k, v in os.environ.items() if k not in ("AMENT_PREFIX_PATH", "COLCON_PREFIX_PATH")}
    out = subprocess.run(["sh", "-c", f". '{prefix}/local_setup.sh' && env -0"], capture_output=True,
                         env=env, timeout=60, check=True).stdout
    return dict(item.split("=", 1) for item in out.decode().split("\0") if "=" in item)


def resolve_like_ros2_run(env: dict[str, str], package: str, executable: str) -> Path:
    """ament index lookup of the package prefix, then <prefix>/lib/<package>/<executable>."""
    for prefix in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix and (Path(prefix) / "share/ament_index/resource_index/packages" / package).is_file():
            path = Path(prefix) / "lib" / package / executable
            assert path.is_file() and os.access(path, os.X_OK), f"{path} is not an executable file"
            return path
    raise AssertionError(f"package {package} not found in AMENT_PREFIX_PATH")


def test_install_layout(install_prefix):
    share = install_prefix / "share" / PKG
    for rel in ("package.xml", "config/genreg.yaml", "config/genreg_objects.yaml", "config/fastdds_large_clouds.xml",
                "launch/genreg.launch.py"):
        assert (share / rel).is_file(), rel
    assert (install_prefix / "share/ament_index/resource_index/packages" / PKG).is_file()
    assert (install_prefix / "lib" / PKG / EXE).is_file()


def test_resolution_agrees_with_ament_index_python(install_prefix, monkeypatch):
    from ament_index_python.packages import get_package_prefix

    env = sourced_env(install_prefix)
    monkeypatch.setenv("AMENT_PREFIX_PATH", env["AMENT_PREFIX_PATH"])
    assert Path(get_package_prefix(PKG)) == install_prefix
    assert resolve_like_ros2_run(env, PKG, EXE) == install_prefix / "lib" / PKG / EXE


def test_ros2_run_starts_publishes_diagnostics_and_exits_on_sigint(install_prefix, untrained_checkpoint,
                                                                   ros_namespace):
    env = sourced_env(install_prefix)
    exe = resolve_like_ros2_run(env, PKG, EXE)
    # The installed copy is the one imported, not the source tree.
    interpreter = exe.read_text().splitlines()[0].removeprefix("#!").strip()
    probe = subprocess.run(
        [interpreter, "-c", "import genreg_ros, genreg_core; print(genreg_ros.__file__); print(genreg_core.__file__)"],
        env=env, capture_output=True, text=True, cwd="/", timeout=60, check=True)
    assert all(line.startswith(str(install_prefix)) for line in probe.stdout.split()), probe.stdout

    ns = f"{ros_namespace}/ros2run"
    params_file = install_prefix / "share" / PKG / "config" / "genreg.yaml"
    cmd = [str(exe), "--ros-args", "--params-file", str(params_file), "-r", f"__ns:={ns}",
           "-p", f"model.checkpoint:={untrained_checkpoint}", "-p", "diagnostics.period:=0.2"]
    proc = subprocess.Popen(cmd, env=env, cwd="/", stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("ros2run_probe", context=ctx)
    got: list[DiagnosticArray] = []
    node.create_subscription(
        DiagnosticArray, "/diagnostics",
        lambda m: got.extend([m] if any(s.hardware_id == f"{ns}/{EXE}" for s in m.status) else []), 10)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        # A fresh install compiles its kernels once (numba's cache beside them is empty): ~20 s here, more under load.
        deadline = time.monotonic() + 180
        while not got and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        if not got:
            proc.kill()
            pytest.fail(f"no diagnostics from {ns}/{EXE} in 180 s; exit code {proc.poll()}; "
                        f"log: {proc.communicate()[1][-3000:]}")
        status = next(s for s in got[-1].status if s.hardware_id == f"{ns}/{EXE}")
        values = {kv.key: kv.value for kv in status.values}
        assert values["registered"] == "0" and values["dropped"] == "0"
    finally:
        executor.shutdown(timeout_sec=2.0)
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "error" not in err.lower(), err
    assert "ready: model" in err  # the node's start-up log line


def test_launch_file_compiles_and_names_the_installed_executable():
    path = REPO / "launch" / "genreg.launch.py"
    py_compile.compile(str(path), doraise=True)
    tree = ast.parse(path.read_text())
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description" for n in tree.body)
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    assert {PKG, EXE, "genreg.yaml", "fastdds_large_clouds.xml"} <= strings
