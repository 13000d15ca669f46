"""Foxglove live (issue 19): the recordings' ``/estimate/pose`` and ``/estimate/state``
topics, with the same schemas and messages (:mod:`mowerhw.recording.mcap`), served by the
Foxglove SDK's WebSocket server, so a layout made for recordings works on the live mower."""

from __future__ import annotations

import json
import logging
import time
from typing import Any

from mowerhw.recording.mcap import SCHEMAS, TOPICS, pose_message, state_message

log = logging.getLogger("mowerhw.web")

#: the topics served live (the others of a recording are raw sensor data)
LIVE_TOPICS = ("/estimate/pose", "/estimate/state")


class FoxgloveLive:
    """A Foxglove WebSocket server publishing each ``live`` update as the two topics."""

    def __init__(self, host: str, port: int) -> None:
        import foxglove

        self._ctx = foxglove.Context()
        self.server = foxglove.start_server(name="mowerhw", host=host, port=port, context=self._ctx)
        self.port = int(self.server.port)
        self.channels = {
            topic: foxglove.Channel(
                topic,
                schema=foxglove.Schema(
                    name=TOPICS[topic],
                    encoding="jsonschema",
                    data=json.dumps(SCHEMAS[TOPICS[topic]]).encode(),
                ),
                message_encoding="json",
                context=self._ctx,
            )
            for topic in LIVE_TOPICS
        }
        self.published = 0
        log.info("web: Foxglove live server on ws://%s:%d", host, self.port)

    def publish(self, live: dict[str, Any]) -> None:
        """One ``live`` update (see :mod:`mowerhw.runtime.live`) as the recordings' messages."""
        pose = live.get("pose")
        now_ns = time.time_ns()
        t = (pose.get("t") if pose else None) or float(live.get("now") or 0.0)
        host_ns = round(t * 1e9)
        if pose:
            msg = pose_message(t, (pose["x"], pose["y"], pose["z"]), pose["q_wxyz"], frame="lawn")
            self.channels["/estimate/pose"].log(msg, log_time=now_ns)
        sigma = pose.get("sigma_xy_m") if pose else None
        state = state_message(
            host_ns,
            str(live.get("mode", "")),
            str(live.get("state", "")),
            bool(live.get("permit")),
            str(live.get("reason", "")),
            float("nan") if sigma is None else float(sigma),
            live.get("signed_distance_m"),
            pose.get("covariance") if pose else None,
        )
        self.channels["/estimate/state"].log(state, log_time=now_ns)
        self.published += 1

    def close(self) -> None:
        self.server.stop()
