"""Bimanual teleoperation: hand frames in, finger/rail/base channels out, at 50 Hz."""

from payload.teleop.calibration import CalibrationError, CalibrationProcedure, Captures
from payload.teleop.channels import BaseChannel, BaseConfig, RailConfig, rail_command
from payload.teleop.filters import OneEuroConfig, OneEuroFilter
from payload.teleop.handmodel import HandModel
from payload.teleop.hands import XR_JOINTS, Hand, HandFrame, HandFrameError
from payload.teleop.replay import HandRecordingWriter, ReplayError, read_hand_recording
from payload.teleop.safety import SafetyConfig, SafetyEvent, TrackingSupervisor

__all__ = [
    "XR_JOINTS",
    "BaseChannel",
    "BaseConfig",
    "CalibrationError",
    "CalibrationProcedure",
    "Captures",
    "Hand",
    "HandFrame",
    "HandFrameError",
    "HandModel",
    "HandRecordingWriter",
    "OneEuroConfig",
    "OneEuroFilter",
    "RailConfig",
    "ReplayError",
    "SafetyConfig",
    "SafetyEvent",
    "TrackingSupervisor",
    "rail_command",
    "read_hand_recording",
]
