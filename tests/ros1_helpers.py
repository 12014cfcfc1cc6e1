"""A roscore on 127.0.0.1 for the ROS 1 node tests, and log messages as ROS 1 dicts."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import time

import numpy as np
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


def ros1_dict(msg):
    """A rosbags message object (as the log reader gives it) as a ROS 1 message dict."""
    fields = getattr(msg, "__dataclass_fields__", None) or getattr(msg, "__slots__", None)
    if isinstance(msg, str | bytes | int | float) or fields is None:
        if isinstance(msg, np.ndarray):
            return msg.tolist()
        if isinstance(msg, list | tuple):
            return [ros1_dict(v) for v in msg]
        return msg
    if set(fields) == {"sec", "nanosec"}:
        return {"secs": msg.sec, "nsecs": msg.nanosec}
    return {k: ros1_dict(getattr(msg, k)) for k in fields if k != "__msgtype__"}
