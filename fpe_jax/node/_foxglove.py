"""`SceneSink`: the track, the observed cars, their predicted paths and 1-sigma ellipses as
Foxglove messages, served live over Foxglove's WebSocket protocol and/or recorded to MCAP.

The messages and topics are `fpe_jax.io.scene`'s (`/track`, `/observations`,
`/predictions/<car>/path`, `/predictions/<car>/ellipses`). Every message's log time is the
stamp it carries, so a recording plays back on the drive's own clock. No JAX is imported.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path

import foxglove
import numpy as np
from foxglove.websocket import ServerListener

from fpe_jax.errors import InputError
from fpe_jax.io import scene

STOP_TIMEOUT_S = 2.0  # the longest `close` waits for the server to let go of its viewers


class _Listener(ServerListener):
    """A new subscription to /track asks for the track again (the WebSocket protocol keeps no
    last message, so a viewer that connects later would not get it). The other callbacks are
    the protocol's no-ops."""

    def __init__(self, resend: threading.Event):
        self._resend = resend

    def on_subscribe(self, client, channel) -> None:
        if channel.topic == scene.TRACK_TOPIC:
            self._resend.set()  # sent by the next call of the sink, not from the server's thread


class SceneSink:
    """Publish the prediction scene to Foxglove: a WebSocket server and/or an MCAP recording.

    Args:
        port: serve Foxglove's WebSocket protocol on this port (0 picks a free one; see `.port`);
            None: no server.
        host: the address to bind (default 127.0.0.1: this machine only).
        mcap_path: record the same messages to this new .mcap file (an existing file is an
            InputError); None: no recording.
        frame_id: the frame of every message (the map frame).

    Calls never wait on a viewer: the SDK queues messages per client and drops the oldest when
    a slow client falls behind, and `close` gives up on a viewer that stopped reading after
    STOP_TIMEOUT_S. Each update does bounded work on the caller's thread (building the
    messages: ~0.2 ms for an observation plus a 10-step prediction, see
    experiments/results/foxglove_sink.md). The methods may be called from several threads.
    """

    def __init__(
        self,
        *,
        port: int | None = None,
        host: str = "127.0.0.1",
        mcap_path: str | os.PathLike | None = None,
        frame_id: str = "map",
    ):
        if port is None and mcap_path is None:
            raise ValueError("SceneSink: nothing to do (give a port, an mcap_path or both)")
        self.frame_id = frame_id
        self.port: int | None = None
        self._context = foxglove.Context()
        self._lock = threading.Lock()
        self._channels: dict = {}
        self._track: tuple[np.ndarray, bool] | None = None
        self._track_due = False  # log the track with the next stamp
        self._resend = threading.Event()
        self._mcap = self._server = None
        self._closed = False
        if mcap_path is not None:
            path = Path(mcap_path)
            if path.exists():
                raise InputError(path, "exists", "a new .mcap file to record to")
            try:
                self._mcap = foxglove.open_mcap(path, context=self._context)
            except Exception as e:  # the SDK raises its own error types for I/O failures
                raise InputError(path, f"cannot be written ({e})") from None
        if port is not None:
            try:
                self._server = foxglove.start_server(
                    name="fpe-jax",
                    host=host,
                    port=port,
                    context=self._context,
                    server_listener=_Listener(self._resend),
                )
            except Exception as e:
                self._close_mcap()
                raise InputError(
                    f"{host}:{port}", f"cannot serve Foxglove's WebSocket protocol ({e})"
                ) from None
            self.port = self._server.port

    # ---- the scene -------------------------------------------------------------------------

    def track(self, centre_xy_m: np.ndarray, closed: bool = False) -> None:
        """The track's centre line (N, 2) x [m], y [m], once at start; `closed` draws a loop.

        Logged with the first observation's or prediction's stamp (so a recording starts with
        it), and again whenever a viewer subscribes to /track."""
        xy = np.array(centre_xy_m, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2 or not np.isfinite(xy).all():
            raise ValueError(f"SceneSink.track: centre line {xy.shape}, expected finite (N, 2)")
        with self._lock:
            self._track = (xy, bool(closed))
            self._track_due = True

    def observation(
        self, car_id: str, stamp_ns: int | np.integer, x_m: float, y_m: float, yaw_rad: float
    ) -> None:
        """An observed pose of `car_id` at `stamp_ns` [ns] (yaw NaN: heading unknown)."""
        msg = scene.foxglove_observation(car_id, stamp_ns, x_m, y_m, yaw_rad, self.frame_id)
        self._log(int(stamp_ns), [(scene.OBSERVATIONS_TOPIC, msg)])

    def prediction(
        self,
        car_id: str,
        stamp_ns: int | np.integer,
        poses: np.ndarray,
        cov_xy_m2: np.ndarray,
        step_stamps_ns: np.ndarray,
        valid: bool = True,
    ) -> None:
        """One prediction of `car_id` made from the observation stamped `stamp_ns` [ns].

        Args:
            poses: (H, 3) predicted x [m], y [m], yaw [rad].
            cov_xy_m2: (H, 2, 2) map-frame covariance of each predicted position [m^2]
                (NaN where none: no ellipse).
            step_stamps_ns: (H,) int time each step predicts [ns].
            valid: False draws the prediction grey, without path or ellipses
                (`fpe_jax.io.scene`).
        """
        drawn = scene.prediction_scene(stamp_ns, poses, cov_xy_m2, step_stamps_ns, valid)
        msgs = scene.foxglove_prediction(car_id, int(stamp_ns), drawn, self.frame_id)
        self._log(int(stamp_ns), msgs)

    def close(self) -> None:
        """Finish the recording and stop the server (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._track_due:  # nothing stamped came: the track alone, at the current time
                self._send_track(time.time_ns())
        self._close_mcap()
        if self._server is not None:
            # stop() waits for every client to take its queued messages: a viewer that stopped
            # reading would hold it (and Ctrl-C of a node) for as long as its connection lives
            stopper = threading.Thread(target=self._server.stop, daemon=True)
            stopper.start()
            stopper.join(STOP_TIMEOUT_S)
            if stopper.is_alive():
                logging.getLogger(__name__).warning(
                    "Foxglove server on port %s: a viewer is not reading; closed without it",
                    self.port,
                )

    def __enter__(self) -> SceneSink:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- internals -------------------------------------------------------------------------

    def _close_mcap(self) -> None:
        if self._mcap is not None:
            self._mcap.close()
            self._mcap = None

    def _channel(self, topic: str, msg):
        ch = self._channels.get(topic)
        if ch is None:
            import foxglove.channels as fc

            kind = getattr(fc, f"{type(msg).__name__}Channel")
            ch = self._channels[topic] = kind(topic, context=self._context)
        return ch

    def _send_track(self, stamp_ns: int | np.integer) -> None:
        xy, closed = self._track
        msg = scene.foxglove_track(xy, stamp_ns, self.frame_id, closed)
        self._channel(scene.TRACK_TOPIC, msg).log(msg, log_time=stamp_ns)
        self._track_due = False

    def _log(self, stamp_ns: int | np.integer, msgs) -> None:
        with self._lock:
            if self._closed:
                return
            if self._resend.is_set():
                self._resend.clear()
                self._track_due = self._track is not None
            if self._track_due:
                self._send_track(stamp_ns)
            for topic, msg in msgs:
                self._channel(topic, msg).log(msg, log_time=stamp_ns)
