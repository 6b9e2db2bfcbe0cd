"""The outside observer: metrics from ground truth, the run monitor, the summary, statistics
across trials and the map picture. Nothing here is read by a robot."""
