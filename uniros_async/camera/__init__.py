"""Cameras as sensors: camera topics (topic.py), sim cameras rendered from the arm's MJCF (sim.py), and real
cameras captured through OpenCV (capture.py, the ``camera`` extra). docs/howto/cameras.md shows them in use."""

from __future__ import annotations

from uniros_async.camera.sim import CAMERA_TOPIC_NAMES, SimCameraConfig, SimCameraNode, open_sim_cameras
from uniros_async.camera.topic import FrameError, FrameSpec, ImagePublisher, camera_topic, frame_age_ns

__all__ = [
    "CAMERA_TOPIC_NAMES",
    "FrameError",
    "FrameSpec",
    "ImagePublisher",
    "SimCameraConfig",
    "SimCameraNode",
    "camera_topic",
    "frame_age_ns",
    "open_sim_cameras",
]
