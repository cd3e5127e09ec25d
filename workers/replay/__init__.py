"""The replay side of ControlVAE and PULSE: the replay buffer (`buffer`: windows that never cross a reset, a clip
switch or a gap) and ControlVAE's data balancing over it (`balancing`: Eq. 18's returns, Eq. 19's frame values)."""
