"""Sweeps: the Hydra callback that opens a multirun's MLflow parent run and compares its points at the end
(`callback`), the shared tables and figures of that comparison (`report`), and the papers' own figures and
statements beside our numbers: PhysicsVAE's alpha ablation (`physicsvae`) and the task presets' sigma and
prior ablations (`tasks`).
"""
