"""Batched closed-loop kinematics (`m3t1r.model.batch_kinematics`): tests aimed at its mutants."""
