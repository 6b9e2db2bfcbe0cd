"""One robot's brain (SLAM + virtual map + planner + motion) and the team data it shares."""
