"""Readers of real instruments' files, and their conversion to the project's measurement table.

One module per format (`delimited`, `optitrack`, `vicon`, `c3d`, `spatial_analyzer`, `rosbag`),
each returning a `TrackerRecord` in SI units; `robot_log` reads the robot's joints; `dwells` turns
streams into static poses and pairs two clocks; `conversion.convert_campaign` puts them together
for `m3t1r convert`. The C3D and ROS 2 bag readers need the `m3t1r[formats]` extra.
"""
