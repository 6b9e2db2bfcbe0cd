"""Decision making (paper Sec. IV-B..D): frontier candidates, rendezvous, the EM step
(Algorithm 1), the utilities U_M (Algorithm 2), U_T, U_D, the planners and motion control."""
