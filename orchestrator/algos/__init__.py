"""Methods as plug-ins, one module per method named by its paper: `controlvae`, `amp`, `tracker`, `physicsvae`
(its simulation layer and its VAE), `pulse`, `task`, and `demos` (an expert's demonstrations); `onpolicy` is the
PPO iteration that amp, tracker and the task's PPO trainer share. `base` holds the contract: `Method`,
`Component` and `TrainerAPI`, what a method may call on the trainer.
"""
