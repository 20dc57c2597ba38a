"""Small numeric helpers of the simulation: finiteness, Gaussian smoothing, smooth noise, and
stacks of rotations about one axis."""

from __future__ import annotations

import math

import numpy as np

from app.domain.frames import FloatArray

# --------------------------------------------------------------------------- small helpers


def finite(value: object) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def gaussian_kernel(sigma_samples: float, half_width: int) -> FloatArray:
    """Normalized (sum 1) Gaussian kernel of 2·half_width + 1 taps."""
    taps = np.arange(-half_width, half_width + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (taps / max(sigma_samples, 1e-9)) ** 2)
    return np.asarray(kernel / kernel.sum(), dtype=np.float64)


def gaussian_smooth(signal: FloatArray, sigma_samples: float) -> FloatArray:
    """``signal`` low-passed by a Gaussian of ``sigma_samples``, ends padded with their values."""
    half_width = math.ceil(3 * sigma_samples)
    padded = np.pad(signal, half_width, mode="edge")
    return np.convolve(padded, gaussian_kernel(sigma_samples, half_width), mode="valid")


def smooth_noise(
    rng: np.random.Generator, n: int, sigma: float, correlation_samples: float
) -> FloatArray:
    """(n,) stationary Gaussian noise of std ``sigma``, correlated over ``correlation_samples``.

    Always draws the same numbers from ``rng`` whatever ``sigma`` (zero included), so a noise level
    never shifts the random stream of anything else.
    """
    half_width = math.ceil(3 * correlation_samples)
    kernel = gaussian_kernel(correlation_samples, half_width)
    white = rng.standard_normal(n + 2 * half_width)
    smooth = np.convolve(white, kernel, mode="valid") / float(np.linalg.norm(kernel))
    return np.asarray(sigma * smooth, dtype=np.float64)


def rotations_about_x(angle_rad: FloatArray) -> FloatArray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out = np.zeros((angle_rad.shape[0], 3, 3))
    out[:, 0, 0] = 1.0
    out[:, 1, 1], out[:, 1, 2], out[:, 2, 1], out[:, 2, 2] = c, -s, s, c
    return out


def rotations_about_y(angle_rad: FloatArray) -> FloatArray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out = np.zeros((angle_rad.shape[0], 3, 3))
    out[:, 1, 1] = 1.0
    out[:, 0, 0], out[:, 0, 2], out[:, 2, 0], out[:, 2, 2] = c, s, -s, c
    return out


def rotations_about_z(angle_rad: FloatArray) -> FloatArray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out = np.zeros((angle_rad.shape[0], 3, 3))
    out[:, 2, 2] = 1.0
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    return out
