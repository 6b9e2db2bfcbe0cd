"""One robot's brain (SLAM + virtual map + planner + motion), its checks of received input,
its view of the team's liveness and its recovery after a restart."""
