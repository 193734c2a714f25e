"""The model of the machine: nominal design, URDF + closures description, closed-loop kinematics (exact and
batch), URDF writing, workspace sampling and the local POE view of the joint placements."""
