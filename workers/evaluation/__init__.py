"""Evaluation: the papers' protocols, one module per thing evaluated, most run in the batched simulator.

- `controller`: a VAE controller. Time until fall with z from the prior
  (PhysicsVAE Fig. 9, §5.5.1); tracking error over 2-second segments with the
  posterior mean (ControlVAE Fig. 14); random sampling from dataset states
  (ControlVAE Fig. 5).
- `pose_error`: AMP's pose error (Peng et al. 2021, Eq. 10) after dynamic time
  warping, on plain arrays.
- `imitation`: an imitation policy's episodes scored by that pose error (AMP
  Table 3).
- `success`: PULSE's imitation metrics (Luo et al. 2024, Table 1, after PHC):
  success rate, E_g-mpjpe and E_mpjpe of any actor tracking every clip.
- `tasks`: a task policy on a frozen decoder over a fixed set of goals (ControlVAE
  §4, PhysicsVAE §4, PULSE §4): normalised return, success, the style score (the
  helper branch's deviation from the decoder, PhysicsVAE Eq. 2) and time until fall.
- `render`: the evaluation videos, recorded as the protocols above run and
  rendered offscreen.

No re-exports here: importing `workers.evaluation.render` loads neither torch nor
the other protocols (the video process renders without them).
"""
