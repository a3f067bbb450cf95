"""The TurtleBot-like robot: a URDF that swarmmap writes (TurtleBot3 Burger dimensions).

Links: ``base_footprint`` (the ground point the path drives), ``base_link`` (the 138 x 178 mm
body), two wheels, a caster, and ``base_scan``, the LDS-01 LiDAR 172 mm above the floor,
32 mm behind the centre, as on the real robot. The world moves it kinematically along its
path; its collision shapes are kept out of the LiDAR's rays (collision group 2).
"""

from __future__ import annotations

from pathlib import Path

LIDAR_LINK = "base_scan"
LIDAR_OFFSET = (-0.032, 0.0, 0.172)
FOOTPRINT_RADIUS_M = 0.105


def _link(name: str, geometry: str, xyz: str, mass: float, colour: str) -> str:
    return f"""  <link name="{name}">
    <visual><origin xyz="{xyz}"/><geometry>{geometry}</geometry><material name="{name}_m"><color rgba="{colour}"/></material></visual>
    <collision><origin xyz="{xyz}"/><geometry>{geometry}</geometry></collision>
    <inertial><mass value="{mass}"/><inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial>
  </link>
"""


def _joint(name: str, parent: str, child: str, xyz: str, rpy: str = "0 0 0") -> str:
    return f"""  <joint name="{name}" type="fixed">
    <parent link="{parent}"/><child link="{child}"/><origin xyz="{xyz}" rpy="{rpy}"/>
  </joint>
"""


def turtlebot_urdf() -> str:
    """The robot's URDF text."""
    lx, ly, lz = LIDAR_OFFSET
    parts = [
        '<?xml version="1.0"?>\n<robot name="swarmmap_turtlebot">\n',
        '  <link name="base_footprint"><inertial><mass value="0.001"/>'
        '<inertia ixx="1e-6" ixy="0" ixz="0" iyy="1e-6" iyz="0" izz="1e-6"/></inertial></link>\n',
        _link("base_link", '<box size="0.138 0.178 0.143"/>', "-0.032 0 0.0795", 0.8, "0.2 0.2 0.2 1"),
        _joint("base_joint", "base_footprint", "base_link", "0 0 0.010"),
        _link("wheel_left", '<cylinder radius="0.033" length="0.018"/>', "0 0 0", 0.03, "0.1 0.1 0.1 1"),
        _joint("wheel_left_joint", "base_link", "wheel_left", "0 0.08 0.023", "-1.5708 0 0"),
        _link("wheel_right", '<cylinder radius="0.033" length="0.018"/>', "0 0 0", 0.03, "0.1 0.1 0.1 1"),
        _joint("wheel_right_joint", "base_link", "wheel_right", "0 -0.08 0.023", "-1.5708 0 0"),
        _link("caster", '<sphere radius="0.005"/>', "0 0 0", 0.005, "0.1 0.1 0.1 1"),
        _joint("caster_joint", "base_link", "caster", "-0.081 0 -0.004"),
        _link(LIDAR_LINK, '<cylinder radius="0.035" length="0.04"/>', "0 0 -0.0175", 0.11, "0.8 0.1 0.1 1"),
        _joint("scan_joint", "base_footprint", LIDAR_LINK, f"{lx} {ly} {lz}"),
        "</robot>\n",
    ]
    return "".join(parts)


def write_urdf(folder: Path) -> Path:
    """Write the URDF into ``folder`` and return its path."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "turtlebot.urdf"
    path.write_text(turtlebot_urdf())
    return path
