"""Per-robot team SLAM: the factor graph on iSAM2 that each robot keeps of the whole team."""
