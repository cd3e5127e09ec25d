"""The simulation: the character, the batched simulator, state features, terrain, a gymnasium adapter."""

from workers.sim.mujoco_log import route_warnings

route_warnings()  # never a MUJOCO_LOG.TXT in the user's working directory
