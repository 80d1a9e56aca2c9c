"""Velocity and acceleration of the jaw from sampled position: differentiators as
small interchangeable classes in a registry (:data:`DIFFERENTIATORS`), looked up by
name with :func:`differentiator`. A new one is one new module with one class."""

from . import gaussian, gradient, savgol  # noqa: F401  (each registers itself)
from .base import (
    DIFFERENTIATORS,
    Differentiator,
    Frozen,
    Kinematics,
    differentiator,
    register,
    sample_interval,
    signal_band_hz,
)
from .gaussian import Gaussian, gaussian_kernels
from .gradient import FiniteDifference
from .savgol import SavitzkyGolay

__all__ = [
    "DIFFERENTIATORS",
    "Differentiator",
    "FiniteDifference",
    "Frozen",
    "Gaussian",
    "Kinematics",
    "SavitzkyGolay",
    "differentiator",
    "gaussian_kernels",
    "register",
    "sample_interval",
    "signal_band_hz",
]
