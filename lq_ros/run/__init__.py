"""Running evaluations: one episode end to end, input validation, and sweeps."""
