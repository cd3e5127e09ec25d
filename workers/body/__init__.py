"""The character's body: its MJCF and index tables (`character`), rotations, and the state features s and
Φ(s) computed from it (`features`). Importing it routes MuJoCo's warnings into logging (`mujoco_log`)."""

from workers.body.mujoco_log import route_warnings

route_warnings()  # never a MUJOCO_LOG.TXT in the user's working directory
