"""Closed-form kinematics of the nominal machine (docs/design.md, "The mechanism"), an oracle independent of
Pinocchio."""

from __future__ import annotations

import math

import numpy as np

from m3t1r.model.design import NOMINAL, MechanismDesign


def forward(sliders: np.ndarray, d: MechanismDesign = NOMINAL) -> np.ndarray:
    """(x, y, z, theta) of P for sliders (B1, B2, B3, B4) [m]; the platform-below-knees branch."""
    s1, s2, s3, s4 = sliders
    knees = []
    for ya, yb in ((d.rail_y0 + s1, d.b2_rail_y + s2), (d.rail_y0 + s3, d.b2_rail_y + s4)):
        knees.append(((ya + yb) / 2, math.sqrt(d.l_u**2 - ((yb - ya) / 2) ** 2)))
    (y1, z1), (y2, z2) = knees
    theta = math.asin((y2 - y1) / d.a)
    c = d.a / 2 * math.cos(theta)
    # P's (x, z) is where two circles of radius l_d about (c, z1) and (b - c, z2) meet.
    c1, c2 = np.array([c, z1]), np.array([d.b - c, z2])
    half = np.linalg.norm(c2 - c1) / 2
    normal = np.array([-(c2 - c1)[1], (c2 - c1)[0]]) / (2 * half)
    mid, h = (c1 + c2) / 2, math.sqrt(d.l_d**2 - half**2)
    x, z = min((mid + h * normal, mid - h * normal), key=lambda p: p[1])
    return np.array([x, (y1 + y2) / 2, z, theta])


def inverse(pose: np.ndarray, d: MechanismDesign = NOMINAL) -> np.ndarray:
    """Sliders (B1, B2, B3, B4) [m] putting P at (x, y, z, theta)."""
    x, y, z, theta = pose
    half = d.a / 2 * np.array([math.cos(theta), math.sin(theta)])
    sliders = []
    for (ax, ay), rail_x in (((x - half[0], y - half[1]), 0.0), ((x + half[0], y + half[1]), d.b)):
        z_knee = z + math.sqrt(d.l_d**2 - (ax - rail_x) ** 2)
        reach = math.sqrt(d.l_u**2 - z_knee**2)
        sliders += [ay - reach - d.rail_y0, ay + reach - d.b2_rail_y]
    return np.array(sliders)
