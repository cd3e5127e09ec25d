"""Evaluation in the loop: the papers' protocols (`workers.evaluation`) run on a method's current weights and
turned into metrics, JSON and figures (`protocols`: controllers and PPO policies; `tasks`: task policies), and
the MP4s of what they show (`video`, rendered offscreen in a child process)."""
