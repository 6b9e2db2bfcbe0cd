"""The simulated world: environment and kinematics, sensors, the world's step, the numeric wire
path between world and robot, and the whole team in one process (em-sim)."""
