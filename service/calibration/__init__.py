"""The robot's model from its own data: servo identification from a recording, the overlay it
writes beside the robot's config, and the run-time check of the simulated joints against the
measured ones."""

from .overlay import calibration_report, write_overlay
from .servos import SERVO_SETTINGS, ServoFit, fit_servos

__all__ = ["SERVO_SETTINGS", "ServoFit", "calibration_report", "fit_servos", "write_overlay"]
