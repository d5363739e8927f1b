"""The robot interface: a robot's topics described in YAML, observations built from them, and the
LIBERO delta action turned into a Cartesian target."""
