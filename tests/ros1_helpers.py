"""A roscore on 127.0.0.1 for the ROS 1 node tests."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import time

import pytest


def ros1_missing() -> str | None:
    """Why ROS 1 cannot be tested here, or None."""
    if shutil.which("roscore") is None:
        return "roscore is not installed (apt-get install ros-core python3-roslaunch)"
    try:
        import fpe_jax.node._ros1  # noqa: F401
    except Exception as e:
        return f"rospy cannot be imported: {e}"
    return None


def need_ros1() -> None:
    """Skip locally, fail in CI (CI set), when ROS 1 is missing."""
    why = ros1_missing()
    if why is None:
        return
    if os.environ.get("CI"):
        pytest.fail(f"CI needs ROS 1: {why}")
    pytest.skip(why)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def roscore(tmp_path):
    """Start `roscore -p PORT` on 127.0.0.1; yields the environment for its clients."""
    port = free_port()
    env = dict(os.environ)
    env.update(
        ROS_MASTER_URI=f"http://127.0.0.1:{port}",
        ROS_IP="127.0.0.1",
        ROS_HOSTNAME="127.0.0.1",
        ROS_HOME=str(tmp_path / "ros_home"),
        ROS_LOG_DIR=str(tmp_path / "ros_log"),
    )
    proc = subprocess.Popen(
        ["roscore", "-p", str(port)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.1)
        else:
            raise RuntimeError("roscore did not start within 30 s")
        yield env
    finally:
        os.killpg(proc.pid, 15)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
            proc.wait()


def node_connections(node_name: str = "/future_pose_estimator") -> set[tuple[str, str]]:
    """{(topic, "i" or "o")}: the connections a running ROS 1 node holds by its own account (its
    getBusInfo), in (subscribed) and out (published); empty while it is not registered. A
    publisher counts a subscriber only once it holds the connection, which can be later than the
    subscriber sees it: this is what the node's own publisher sees."""
    import xmlrpc.client

    import rosgraph.masterapi

    master = rosgraph.masterapi.Master("/fpe_test_bus_info")
    try:
        uri = master.lookupNode(node_name)
    except rosgraph.masterapi.Error:
        return set()
    _code, _msg, info = xmlrpc.client.ServerProxy(uri).getBusInfo("/fpe_test_bus_info")
    return {(c[4], c[2]) for c in info}
