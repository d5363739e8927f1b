"""Simulated robots: the LIBERO task env (MuJoCo via robosuite) and the wall-clock robot stand-in."""
