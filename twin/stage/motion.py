"""Stage motion as the firmware makes it: coordinated trapezoidal moves of both axes.

The stage controller speaks Grbl (DESIGN.md), and a Grbl ``G1`` move interpolates all axes along
one straight path in joint space: one trapezoidal velocity profile in the path parameter s in
[0, 1], limited by every axis's maximum speed and acceleration scaled by its share of the move.
Both axes therefore start and arrive together. SI inside (m, rad, s).

Bench settings shared with the firmware (bench_fw): X 10 mm/s, 50 mm/s^2, travel +-50 mm around
the reference; A (yaw) 20 deg/s, 40 deg/s^2, travel +-30 deg around the reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twin.core.errors import AimbenchError


class StageLimitError(AimbenchError):
    """A commanded stage position lies outside the stage's travel."""


@dataclass(frozen=True)
class AxisSettings:
    """One stepper axis: limits as configured in the firmware (Grbl $110/$120/$130 analogues)."""

    max_speed: float  # m/s or rad/s
    acceleration: float  # m/s^2 or rad/s^2
    travel_min: float  # m or rad, relative to the bench reference
    travel_max: float

    def check(self, name: str, value: float, unit_scale: float, unit: str) -> None:
        """Raise `StageLimitError` if ``value`` is outside the travel (message in edge units)."""
        if not self.travel_min - 1e-12 <= value <= self.travel_max + 1e-12:
            raise StageLimitError(
                f"{name} = {value * unit_scale:.3f} {unit} is outside the travel "
                f"[{self.travel_min * unit_scale:.1f}, {self.travel_max * unit_scale:.1f}] {unit};"
                f" command a position inside it")


#: Linear stage X (bench settings shared with the firmware engineer).
X_AXIS = AxisSettings(max_speed=0.010, acceleration=0.050, travel_min=-0.050, travel_max=0.050)
#: Rotation stage A (yaw).
YAW_AXIS = AxisSettings(max_speed=math.radians(20.0), acceleration=math.radians(40.0),
                        travel_min=math.radians(-30.0), travel_max=math.radians(30.0))


@dataclass(frozen=True)
class Trapezoid:
    """A 1-D trapezoidal (or triangular) profile from 0 to ``length`` (> = 0).

    ``v`` is the cruise speed reached (< = v_max), ``t_acc`` the ramp time, ``duration`` the total.
    """

    length: float
    v: float
    a: float
    t_acc: float
    duration: float

    @classmethod
    def plan(cls, length: float, v_max: float, a_max: float) -> Trapezoid:
        length = abs(length)
        if length == 0.0:
            return cls(0.0, 0.0, a_max, 0.0, 0.0)
        if length >= v_max**2 / a_max:  # reaches cruise speed
            t_acc = v_max / a_max
            return cls(length, v_max, a_max, t_acc, 2 * t_acc + (length - v_max * t_acc) / v_max)
        t_acc = math.sqrt(length / a_max)  # triangular: never reaches v_max
        return cls(length, a_max * t_acc, a_max, t_acc, 2 * t_acc)

    def position(self, t: np.ndarray | float) -> np.ndarray:
        """Distance travelled at time t (s) since the start, clamped to [0, length]."""
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration)
        if self.duration == 0.0:
            return np.zeros_like(t) + self.length
        t_dec = self.duration - self.t_acc
        acc = 0.5 * self.a * t**2
        cruise = 0.5 * self.a * self.t_acc**2 + self.v * (t - self.t_acc)
        td = self.duration - t
        dec = self.length - 0.5 * self.a * td**2
        return np.where(t < self.t_acc, acc, np.where(t < t_dec, cruise, dec))

    def velocity(self, t: np.ndarray | float) -> np.ndarray:
        """Speed at time t (s), > = 0."""
        t = np.asarray(t, dtype=float)
        if self.duration == 0.0:
            return np.zeros_like(t)
        v = np.minimum(self.a * t, np.minimum(self.v, self.a * (self.duration - t)))
        return np.where((t < 0) | (t > self.duration), 0.0, v)


@dataclass(frozen=True)
class StageMove:
    """A coordinated move of (x, yaw) from ``start`` to ``end``: both axes arrive together."""

    start: tuple[float, float]
    end: tuple[float, float]
    profile: Trapezoid  # in the path parameter s (length 1)

    @classmethod
    def plan(cls, start: tuple[float, float], end: tuple[float, float],
             axes: tuple[AxisSettings, AxisSettings] = (X_AXIS, YAW_AXIS)) -> StageMove:
        """Grbl-style coordinated move; raises `StageLimitError` if ``end`` is out of travel."""
        axes[0].check("x", end[0], 1e3, "mm")
        axes[1].check("yaw", end[1], 180.0 / math.pi, "deg")
        delta = np.subtract(end, start)
        moving = np.abs(delta) > 0
        if not moving.any():
            return cls(tuple(start), tuple(end), Trapezoid.plan(0.0, 1.0, 1.0))
        # Limits of the path parameter s: each axis's limit divided by its share of the move.
        shares = [(ax, abs(d)) for ax, d, mv in zip(axes, delta, moving, strict=True) if mv]
        v_s = min(ax.max_speed / d for ax, d in shares)
        a_s = min(ax.acceleration / d for ax, d in shares)
        return cls(tuple(map(float, start)), tuple(map(float, end)), Trapezoid.plan(1.0, v_s, a_s))

    @property
    def duration(self) -> float:
        return self.profile.duration

    def at(self, t: np.ndarray | float) -> np.ndarray:
        """Setpoint (x, yaw) at time t (s) since the move started; shape (..., 2)."""
        s = self.profile.position(t)
        return np.asarray(self.start) + np.multiply.outer(s, np.subtract(self.end, self.start))

    def rate_at(self, t: np.ndarray | float) -> np.ndarray:
        """Setpoint rate (x_dot, yaw_dot) at time t, shape (..., 2)."""
        s_dot = self.profile.velocity(t)
        return np.multiply.outer(s_dot, np.subtract(self.end, self.start))
