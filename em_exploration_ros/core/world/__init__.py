"""The simulated world (truth side only): environment and kinematics, seeded sensors and the
world's step. No robot process reads ground truth from it."""
