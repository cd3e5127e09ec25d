"""Downstream tasks on a frozen skill model: their goals and success rules (`goals`: heading, steering, point goal,
strike, VR tracking) and the rollout policies that pursue them (`policy`: the prior-residual task policy and its
PPO twin)."""
