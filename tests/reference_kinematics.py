"""Reference kinematics of the example mechanisms (m3t1r.model.examples), independent of m3t1r's solver.

Only the geometry numbers come from the examples module; the math here is numpy/scipy only:

- five-bar: closed-form forward (circle intersection) and inverse (one circle intersection per leg);
- spherical wrist: forward by scipy.optimize on the platform orientation (the three conditions
  w_i . R p_i = cos(distal angle)), followed along a straight motor path from home; inverse in
  closed form per leg (A cos(theta) + B sin(theta) = C).

Branches are those of the examples' home: five-bar elbows out, effector on the left of
elbow 1 -> elbow 2; wrist legs on the `+acos` branch of the closed-form inverse.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from m3t1r.model.examples import FiveBarGeometry, SphericalWristGeometry

FIVE_BAR = FiveBarGeometry()
WRIST = SphericalWristGeometry()


# ---------------------------------------------------------------------------------------------
# Rotations


def rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def exp_so3(r: np.ndarray) -> np.ndarray:
    """Rotation by |r| about r (Rodrigues)."""
    angle = float(np.linalg.norm(r))
    k = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if angle < 1e-9:  # second-order series: exact to rounding at this size
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + math.sin(angle) / angle * k + (1.0 - math.cos(angle)) / angle**2 * k @ k


def rotation_angle(r: np.ndarray) -> float:
    """Angle [rad] of a rotation matrix, accurate near zero (from the skew part)."""
    skew = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2.0
    return math.atan2(float(np.linalg.norm(skew)), (float(np.trace(r)) - 1.0) / 2.0)


# ---------------------------------------------------------------------------------------------
# Five-bar


def _meet(c1: np.ndarray, r1: float, c2: np.ndarray, r2: float, left: bool) -> np.ndarray | None:
    """Intersection of two circles on the left (or right) of c1 -> c2; None if they do not meet."""
    dx, dy = c2 - c1
    dist = math.hypot(dx, dy)
    a = (r1 * r1 - r2 * r2 + dist * dist) / (2.0 * dist)
    h2 = r1 * r1 - a * a
    if h2 <= 0.0:
        return None
    h = math.sqrt(h2) * (1.0 if left else -1.0)
    return np.array([c1[0] + (a * dx - h * dy) / dist, c1[1] + (a * dy + h * dx) / dist])


def five_bar_anchors(g: FiveBarGeometry = FIVE_BAR) -> tuple[np.ndarray, np.ndarray]:
    return np.array([-g.base_distance / 2, 0.0]), np.array([g.base_distance / 2, 0.0])


def five_bar_elbows(motors: np.ndarray, g: FiveBarGeometry = FIVE_BAR) -> tuple[np.ndarray, np.ndarray]:
    a1, a2 = five_bar_anchors(g)
    return (
        a1 + g.proximal * np.array([math.cos(motors[0]), math.sin(motors[0])]),
        a2 + g.proximal * np.array([math.cos(motors[1]), math.sin(motors[1])]),
    )


def five_bar_forward(motors: np.ndarray, g: FiveBarGeometry = FIVE_BAR) -> np.ndarray:
    """Effector (x, y) [m] for motor angles [rad]; raises ValueError if the loop cannot close."""
    b1, b2 = five_bar_elbows(motors, g)
    point = _meet(b1, g.distal, b2, g.distal, left=True)
    if point is None:
        raise ValueError(f"the five-bar does not assemble at motors {motors}")
    return point


def five_bar_inverse(point: np.ndarray, g: FiveBarGeometry = FIVE_BAR) -> np.ndarray:
    """Motor angles [rad] putting the effector at (x, y) [m], elbows out."""
    motors = []
    for anchor, left in zip(five_bar_anchors(g), (True, False)):
        elbow = _meet(anchor, g.proximal, np.asarray(point, dtype=float), g.distal, left)
        if elbow is None:
            raise ValueError(f"leg cannot reach {point}")
        motors.append(math.atan2(elbow[1] - anchor[1], elbow[0] - anchor[0]))
    return np.array(motors)


def five_bar_singularity_measures(motors: np.ndarray, g: FiveBarGeometry = FIVE_BAR) -> tuple[float, float, float]:
    """(parallel, serial leg 1, serial leg 2): sines of the distal-distal and proximal-distal angles."""
    point = five_bar_forward(motors, g)
    cross = lambda a, b: float(a[0] * b[1] - a[1] * b[0])
    d1, d2 = [(point - b) / g.distal for b in five_bar_elbows(motors, g)]
    p1, p2 = [np.array([math.cos(m), math.sin(m)]) for m in motors]
    return cross(d1, d2), cross(p1, d1), cross(p2, d2)


# ---------------------------------------------------------------------------------------------
# Spherical wrist


def _motor_frame(leg: int, g: SphericalWristGeometry) -> np.ndarray:
    return rz(2.0 * math.pi * (leg - 1) / 3.0) @ ry(g.base_cone)


def wrist_motor_axis(leg: int, g: SphericalWristGeometry = WRIST) -> np.ndarray:
    return _motor_frame(leg, g)[:, 2]


def wrist_elbow_axis(leg: int, motor: float, g: SphericalWristGeometry = WRIST) -> np.ndarray:
    """w_i: the elbow axis (base frame) at the motor angle [rad]."""
    k = np.array([0.0, -math.sin(g.proximal_angle), math.cos(g.proximal_angle)])
    return _motor_frame(leg, g) @ rz(motor) @ k


def wrist_platform_axis(leg: int, g: SphericalWristGeometry = WRIST) -> np.ndarray:
    """p_i: the distal axis of leg `leg` in platform coordinates."""
    azimuth = 2.0 * math.pi * (leg - 1) / 3.0 + g.platform_twist
    s = math.sin(g.platform_cone)
    return np.array([s * math.cos(azimuth), s * math.sin(azimuth), math.cos(g.platform_cone)])


def wrist_conditions(rotation: np.ndarray, motors: np.ndarray, g: SphericalWristGeometry = WRIST) -> np.ndarray:
    """w_i . R p_i - cos(distal angle), i = 1..3: zero when every leg closes."""
    return np.array(
        [wrist_elbow_axis(leg, motors[leg - 1], g) @ rotation @ wrist_platform_axis(leg, g) for leg in (1, 2, 3)]
    ) - math.cos(g.distal_angle)


def _solve_near(rotation: np.ndarray, motors: np.ndarray, g: SphericalWristGeometry) -> np.ndarray:
    fit = least_squares(
        lambda r: wrist_conditions(exp_so3(r) @ rotation, motors, g),
        np.zeros(3),
        method="lm",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    return exp_so3(fit.x) @ rotation


def wrist_forward(motors: np.ndarray, g: SphericalWristGeometry = WRIST, steps: int = 8) -> np.ndarray:
    """Platform orientation (3x3, base frame) at the motor angles [rad], on the home assembly branch.

    The branch is followed from the motors (pi/4, pi/4, pi/4), where the default (agile-eye)
    platform is the identity, along a straight motor path in `steps` solves.
    """
    start = np.full(3, math.pi / 4)
    rotation = _solve_near(np.eye(3), start, g)
    for s in np.linspace(0.0, 1.0, steps + 1)[1:]:
        rotation = _solve_near(rotation, start + s * (np.asarray(motors, dtype=float) - start), g)
    worst = float(np.max(np.abs(wrist_conditions(rotation, motors, g))))
    if worst > 1e-13:
        raise ValueError(f"the reference wrist FK did not converge at {motors}: residual {worst:.2e}")
    return rotation


def wrist_inverse(rotation: np.ndarray, g: SphericalWristGeometry = WRIST, branch: int = 1) -> np.ndarray:
    """Motor angles [rad] for a platform orientation: A cos(t) + B sin(t) = C per leg, `+acos` branch."""
    k = np.array([0.0, -math.sin(g.proximal_angle), math.cos(g.proximal_angle)])
    motors = []
    for leg in (1, 2, 3):
        v = _motor_frame(leg, g).T @ rotation @ wrist_platform_axis(leg, g)
        # Rz(t) k = (-k_y sin t, k_y cos t, k_z) (k_x = 0)
        a, b, c = k[1] * v[1], -k[1] * v[0], math.cos(g.distal_angle) - k[2] * v[2]
        radius = math.hypot(a, b)
        if abs(c) > radius:
            raise ValueError(f"leg {leg} cannot reach this orientation")
        motors.append(math.remainder(math.atan2(b, a) + branch * math.acos(c / radius), 2.0 * math.pi))
    return np.array(motors)


def wrist_singularity_measures(
    motors: np.ndarray, rotation: np.ndarray, g: SphericalWristGeometry = WRIST
) -> tuple[float, list[float]]:
    """(parallel, [serial per leg]): det of the unit normals of the planes (w_i, v_i), and det[u_i w_i v_i]."""
    normals, serial = [], []
    for leg in (1, 2, 3):
        u, w = wrist_motor_axis(leg, g), wrist_elbow_axis(leg, motors[leg - 1], g)
        v = rotation @ wrist_platform_axis(leg, g)
        n = np.cross(w, v)
        normals.append(n / np.linalg.norm(n))
        serial.append(float(np.linalg.det(np.array([u, w, v]))))
    return float(np.linalg.det(np.array(normals))), serial
