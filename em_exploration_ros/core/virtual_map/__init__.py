"""The virtual map (paper Sec. IV-A): occupancy log-odds and per-cell landmark covariances."""
