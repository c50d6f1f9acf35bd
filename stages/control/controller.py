"""Force control from tactile force estimates: the paper's grasp controller and slip avoider.

Both controllers read (Fx, Fy, Fz) estimates (N, Fz < 0 pressing) from any predictor with
``reset()`` and ``step(image) -> (3,)`` (a trained force model's streaming predictor, or the
:class:`OraclePredictor` built on a twin's true force) and drive any :class:`Gripper`.  They
are called once per sensor frame and act on their own clock (``rate_hz``).

GraspController (paper: P control at 10 Hz, Kp = 0.0004 m/N, closing at 0.005 m/s): closes
until the measured normal force -Fz reaches ``contact_N``, then every tick commands
width - Kp (target - measured) at the closing speed.  Updating from the current width makes
the width integrate the force error, so the steady state has no offset.

SlipAvoider (paper: 20 Hz, a 0.5 s window, shear variation over three samples > 0.3 N in
either axis -> tighten by 0.001 m at 0.015 m/s): keeps the last ``window_s`` of (Fx, Fy); when
max - min over the last ``samples`` samples exceeds ``threshold_N`` in x or y it tightens, then
clears the history and waits for the tightening to finish, so one disturbance is answered once.
"""
from __future__ import annotations

from collections import deque
from typing import Callable, Protocol

import numpy as np

_EPS = 1e-9


class Predictor(Protocol):
    def reset(self) -> None: ...

    def step(self, image) -> np.ndarray: ...


class OraclePredictor:
    """Force 'prediction' from the twin's true force: `source()` -> (3,) N, scaled by `gain`
    (a model that under- or over-reads), plus a constant bias, Gaussian noise (N, per axis)
    and a lag of whole frames."""

    def __init__(self, source: Callable[[], np.ndarray], *, noise_N: float = 0.0, lag_frames: int = 0,
                 gain: float = 1.0, bias_N=(0.0, 0.0, 0.0), seed: int = 0):
        self.source, self.noise, self.lag = source, float(noise_N), int(lag_frames)
        self.gain, self.bias, self.seed = float(gain), np.asarray(bias_N, float), seed
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self.history = deque(maxlen=self.lag + 1)

    def step(self, image=None) -> np.ndarray:
        self.history.append(np.asarray(self.source(), float))
        value = self.gain * self.history[0] + self.bias + self.noise * self.rng.standard_normal(3)
        return value.astype(np.float32)


class _Clock:
    """Ticks at `rate_hz` on the caller's time stamps."""

    def __init__(self, rate_hz: float):
        self.period, self.next = 1.0 / float(rate_hz), None

    def start(self, t: float) -> None:
        self.next = t

    def due(self, t: float) -> bool:
        if self.next is None or t + _EPS < self.next:
            return False
        while self.next <= t + _EPS:               # a late call skips the missed ticks
            self.next += self.period
        return True


class GraspController:
    """Close, then P control of the gripper width on the measured normal force."""

    def __init__(self, target_N: float, kp: float = 0.0004, rate_hz: float = 10.0,
                 close_speed: float = 0.005, contact_N: float = 0.1, min_width_m: float = 0.0):
        if target_N <= contact_N:
            raise ValueError(f"target force {target_N} N must exceed the contact threshold {contact_N} N")
        self.target, self.kp, self.speed = float(target_N), float(kp), float(close_speed)
        self.contact_N, self.min_width = float(contact_N), float(min_width_m)
        self.clock = _Clock(rate_hz)
        self.phase = "idle"                 # idle -> closing -> control -> hold
        self.contact_t = None

    def start(self, t: float, gripper) -> None:
        """Begin closing at time t."""
        self.phase = "closing"
        self.clock.start(t)
        gripper.move(self.min_width, self.speed)

    def hold(self, gripper) -> None:
        """Stop controlling and keep the current width."""
        self.phase = "hold"
        gripper.stop()

    def update(self, t: float, force, gripper) -> str | None:
        """One sensor frame; returns "contact" on the tick that first feels the object."""
        if self.phase not in ("closing", "control") or not self.clock.due(t):
            return None
        normal = -float(force[2])
        event = None
        if self.phase == "closing":
            if normal < self.contact_N:
                return None
            self.phase, self.contact_t, event = "control", t, "contact"
        width = gripper.width() - self.kp * (self.target - normal)
        gripper.move(max(width, self.min_width), self.speed)
        return event


class SlipAvoider:
    """Detect slip from the shear history and tighten the grasp."""

    def __init__(self, rate_hz: float = 20.0, window_s: float = 0.5, threshold_N: float = 0.3,
                 samples: int = 3, tighten_m: float = 0.001, speed: float = 0.015,
                 min_width_m: float = 0.0):
        if samples < 2:
            raise ValueError(f"slip check needs at least 2 samples, got {samples}")
        self.clock = _Clock(rate_hz)
        self.window = max(int(round(window_s * rate_hz)), samples)
        self.threshold, self.samples = float(threshold_N), int(samples)
        self.tighten, self.speed, self.min_width = float(tighten_m), float(speed), float(min_width_m)
        self.history: deque = deque(maxlen=self.window)
        self.active, self.busy_until, self.detections = False, -np.inf, []

    def start(self, t: float) -> None:
        self.active = True
        self.clock.start(t)
        self.history.clear()

    def stop(self) -> None:
        self.active = False

    def variation(self) -> float:
        """Largest max - min of Fx or Fy over the last `samples` samples (0 if too few)."""
        if len(self.history) < self.samples:
            return 0.0
        last = np.asarray(list(self.history)[-self.samples:])
        return float((last.max(0) - last.min(0)).max())

    def update(self, t: float, force, gripper) -> bool:
        """One sensor frame; True when slip is detected (and a tightening commanded)."""
        if not self.active or not self.clock.due(t) or t + _EPS < self.busy_until:
            return False
        self.history.append((float(force[0]), float(force[1])))
        if self.variation() <= self.threshold:
            return False
        self.detections.append(t)
        gripper.move(max(gripper.width() - self.tighten, self.min_width), self.speed)
        self.busy_until = t + self.tighten / self.speed
        self.history.clear()
        return True
