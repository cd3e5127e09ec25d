"""The components a method runs, as plain classes built from the config inside whatever process hosts them
(this one, or a Ray actor): `rollout` (the rollout worker), `replay` (the replay buffer), and one module per
method's learners (`controlvae`, `physicsvae`, `pulse`, `amp`, `task`; `ppo` is shared by the PPO methods) on
`base` (what every learner actor shares)."""
