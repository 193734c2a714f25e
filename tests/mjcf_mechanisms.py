"""MJCF files of small closed-loop mechanisms, written for the tests (published files are not copied).

- `five_bar_mjcf`: a planar five-bar in the base x-y plane (hinges along z), closed by a `connect`
  at the tip of the left rod, two motors, the effector a site at that tip. Its two chains hang
  from the world side by side (Pinocchio's parser reads only the world's first body on its own).
- `spatial_loop_mjcf`: a spatial single loop of seven hinges with skew axes whose last link is
  welded (`weld`, no body2: the world) where the reference configuration puts it; one motor
  (mobility 7 - 6 = 1), angles in the file's default degrees; two sites (`platform`, `tool`).
- `slider_crank_mjcf`: a slider (slide joint, range in metres under degree angles) driving a
  crank through a rod, closed by a `connect`.
Both close at their reference configuration qpos0, as MuJoCo models do.
- `straight_four_bar_mjcf`: a crank-rocker four-bar published as such files often are, every link
  laid along x at qpos0 and the loop closed by a site-to-site `connect` (the sites `STRAIGHT_GAP`
  apart there), no keyframe: qpos0 is a singular configuration, not an assembly.
"""

from __future__ import annotations

from pathlib import Path

FIVE_BAR_CRANK = 0.2  # [m] crank length (both sides)
FIVE_BAR_ROD = (0.1, 0.15)  # [m] the left rod's tip in its frame; the right rod's is mirrored
FIVE_BAR_BASE = 0.1  # [m] half the distance between the motors


def five_bar_mjcf(
    folder: Path,
    *,
    actuators: str | None = None,
    equality: str | None = None,
    keyframe: str = "",
    name: str = "five_bar",
) -> Path:
    """Write the five-bar MJCF into `folder`; `actuators`/`equality` replace the blocks' content."""
    x, y = FIVE_BAR_ROD
    actuators = (
        '<position name="left" joint="motor_l"/><motor name="right" joint="motor_r"/>'
        if actuators is None
        else actuators
    )
    equality = f'<connect name="tip" body1="rod_l" body2="rod_r" anchor="{x} {y} 0"/>' if equality is None else equality
    text = f"""<mujoco model="{name}">
  <compiler angle="radian"/>
  <option gravity="0 -9.81 0"/>
  <worldbody>
    <body name="crank_l" pos="-{FIVE_BAR_BASE} 0 0">
      <joint name="motor_l" type="hinge" axis="0 0 1" range="-0.3 0.3"/>
      <geom type="capsule" fromto="0 0 0 0 {FIVE_BAR_CRANK} 0" size="0.01"/>
      <body name="rod_l" pos="0 {FIVE_BAR_CRANK} 0">
        <joint name="elbow_l" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 {x} {y} 0" size="0.01"/>
        <site name="effector" pos="{x} {y} 0"/>
      </body>
    </body>
    <body name="crank_r" pos="{FIVE_BAR_BASE} 0 0">
      <joint name="motor_r" type="hinge" axis="0 0 1" range="-0.3 0.3"/>
      <geom type="capsule" fromto="0 0 0 0 {FIVE_BAR_CRANK} 0" size="0.01"/>
      <body name="rod_r" pos="0 {FIVE_BAR_CRANK} 0">
        <joint name="elbow_r" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 -{x} {y} 0" size="0.01"/>
      </body>
    </body>
  </worldbody>
  <equality>{equality}</equality>
  <actuator>{actuators}</actuator>
  {keyframe}
</mujoco>
"""
    path = folder / f"{name}.xml"
    path.write_text(text)
    return path


#: (pos of the body in its parent [m], euler [deg], hinge axis) of the seven links.
_SPATIAL_LINKS = (
    ("0 0 0.1", "0 0 0", "0 0 1"),
    ("0.2 0 0", "20 0 0", "0 1 0"),
    ("0.15 0.05 0", "0 15 30", "1 0 0.3"),
    ("0.1 0.1 0.05", "10 0 0", "0 0 1"),
    ("0 0.15 0", "0 -20 0", "0.2 1 0"),
    ("-0.1 0.1 0", "0 0 25", "1 0 0"),
    ("-0.05 0 -0.1", "15 10 0", "0 0.3 1"),
)


def spatial_loop_mjcf(folder: Path, name: str = "spatial_loop") -> Path:
    """Write the seven-hinge loop welded to the world into `folder`."""
    body = '<site name="tool" pos="0.05 0 0"/>'
    for k, (pos, euler, axis) in reversed(list(enumerate(_SPATIAL_LINKS, start=1))):
        extra = '<site name="platform" pos="0.02 0.03 0"/>' if k == 4 else ""
        limit = ' range="-120 120"' if k == 1 else ""
        body = (
            f'<body name="link{k}" pos="{pos}" euler="{euler}"><joint name="j{k}" type="hinge" axis="{axis}"'
            f'{limit}/><geom type="sphere" size="0.02" mass="0.2"/>{extra}{body}</body>'
        )
    text = f"""<mujoco model="{name}">
  <worldbody>
    <body name="base">{body}</body>
  </worldbody>
  <equality><weld name="anchor" body1="link7"/></equality>
  <actuator><motor name="drive" joint="j1"/></actuator>
</mujoco>
"""
    path = folder / f"{name}.xml"
    path.write_text(text)
    return path


def slider_crank_mjcf(folder: Path, name: str = "slider_crank") -> Path:
    """Write the slider-crank into `folder`: slide range -0.05..0.05 m, `<compiler angle="degree">`."""
    text = f"""<mujoco model="{name}">
  <compiler angle="degree"/>
  <worldbody>
    <body name="slider" pos="0 0 0">
      <joint name="slide" type="slide" axis="1 0 0" range="-0.05 0.05"/>
      <geom type="box" size="0.02 0.02 0.02" mass="0.3"/>
      <body name="rod" pos="0 0 0">
        <joint name="pin" type="hinge" axis="0 0 1" range="-90 90"/>
        <geom type="capsule" fromto="0 0 0 0.25 0.1 0" size="0.01"/>
        <site name="rod_tip" pos="0.25 0.1 0"/>
      </body>
    </body>
    <body name="crank" pos="0.3 0 0">
      <joint name="crank" type="hinge" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 -0.05 0.1 0" size="0.01"/>
    </body>
  </worldbody>
  <equality><connect name="tip" body1="rod" body2="crank" anchor="0.25 0.1 0"/></equality>
  <actuator><motor joint="slide"/></actuator>
</mujoco>
"""
    path = folder / f"{name}.xml"
    path.write_text(text)
    return path


STRAIGHT_FOUR_BAR = (0.1, 0.03, 0.08, 0.07)  # [m] ground, crank, coupler, rocker
STRAIGHT_GAP = STRAIGHT_FOUR_BAR[1] + STRAIGHT_FOUR_BAR[2] - (STRAIGHT_FOUR_BAR[0] - STRAIGHT_FOUR_BAR[3])  # [m]


def straight_four_bar_mjcf(folder: Path, name: str = "straight_four_bar") -> Path:
    """Write the four-bar laid straight into `folder`: motor `crank`, passive `knee` and `rocker`,
    the effector a site `tracer` at the coupler's far end (its cut site `coupler_end`)."""
    ground, crank, coupler, rocker = STRAIGHT_FOUR_BAR
    text = f"""<mujoco model="{name}">
  <worldbody>
    <body name="crank_link">
      <joint name="crank" type="hinge" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 {crank} 0 0" size="0.003"/>
      <body name="coupler_link" pos="{crank} 0 0">
        <joint name="knee" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 {coupler} 0 0" size="0.003"/>
        <site name="coupler_end" pos="{coupler} 0 0"/>
        <site name="tracer" pos="{coupler} 0 0"/>
      </body>
    </body>
    <body name="rocker_link" pos="{ground} 0 0">
      <joint name="rocker" type="hinge" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 {-rocker} 0 0" size="0.003"/>
      <site name="rocker_end" pos="{-rocker} 0 0"/>
    </body>
  </worldbody>
  <equality><connect name="loop" site1="coupler_end" site2="rocker_end"/></equality>
  <actuator><position name="drive" joint="crank"/></actuator>
</mujoco>
"""
    path = folder / f"{name}.xml"
    path.write_text(text)
    (folder / f"{name}.closures.yaml").write_text("platform_frame: tracer\n")
    return path
