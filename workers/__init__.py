"""The data plane: everything that computes (simulation, motion data, networks, losses, learners, the rollout
worker, the replay buffer, evaluation). Plain classes and pure functions; no ray, mlflow or hydra."""
