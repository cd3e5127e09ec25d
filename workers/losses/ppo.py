"""PPO's pure functions: GAE(λ) advantages with TD(λ) returns, the clipped surrogate and value loss.

Shapes use T for time and B for the batch of environments (rollouts are [T, B],
time first), and N for a flat minibatch of samples.

Episode-end convention (`compute_gae`):
  dones[t] = 1        the episode ended after step t, for any reason; row t + 1 of
                      the same column starts a new episode, so nothing is carried
                      back across it.
  truncations[t] = 1  that end was a cut (a time limit), not a terminal state: the
                      target bootstraps from the value of the state the episode
                      actually reached, which the caller passes in
                      `next_values[t]` (`values[t + 1]` belongs to the new episode).
                      A truncation counts as an end even where dones[t] = 0.
  otherwise           an end is terminal: the value after it is zero.
"""

from __future__ import annotations

import torch


def compute_gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    dones: torch.Tensor,
    bootstrap_value: torch.Tensor,
    gamma: float,
    lam: float,
    truncations: torch.Tensor | None = None,
    next_values: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimates and the matching TD(λ) returns.

    Args:
      rewards:         [T, B] r_t.
      values:          [T, B] V(s_t).
      dones:           [T, B] 1 where the episode ended after step t (see the module docstring).
      bootstrap_value: [B] V(s_T), the value of the state after the last step; used
                       where the last step did not end its episode.
      gamma, lam:      discount and GAE λ.
      truncations:     [T, B] optional; 1 where the end after step t was a cut.
      next_values:     [T, B] V of the state reached after step t; required with
                       `truncations` and read only where they are 1.

    Returns:
      advantages [T, B]: A_t = Σ_k (γλ)^k δ_{t+k}, within the episode, with
                         δ_t = r_t + γ V_next,t − V(s_t).
      returns    [T, B]: A_t + V(s_t), the TD(λ) targets for the value function.
    Both are detached from the graph.
    """
    rewards, values, bootstrap_value = rewards.detach(), values.detach(), bootstrap_value.detach()
    ended = dones.to(values.dtype)
    following = torch.cat((values[1:], bootstrap_value.unsqueeze(0)), dim=0)  # [T, B] V(s_{t+1}) when no end
    not_terminal = 1.0 - ended
    if truncations is not None:
        if next_values is None:
            raise ValueError("compute_gae: truncations need next_values (V of the state reached after each step)")
        cut = truncations.to(values.dtype)
        ended = torch.maximum(ended, cut)
        following = torch.where(cut > 0, next_values.detach(), following)
        not_terminal = 1.0 - ended + cut  # a cut bootstraps; a terminal end does not
    deltas = rewards + gamma * following * not_terminal - values
    carry = gamma * lam * (1.0 - ended)  # [T, B] how much of A_{t+1} flows back into A_t
    advantages = torch.zeros_like(values)
    running = torch.zeros_like(bootstrap_value)
    for t in range(values.shape[0] - 1, -1, -1):
        running = deltas[t] + carry[t] * running
        advantages[t] = running
    return advantages, advantages + values


def normalize_advantages(advantages: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """[N] -> [N] with mean 0 and (population) standard deviation 1; a single sample is only centred."""
    centred = advantages - advantages.mean()
    if advantages.numel() < 2:
        return centred
    return centred / (advantages.std(unbiased=False) + eps)


def ppo_loss(
    new_log_prob: torch.Tensor,
    old_log_prob: torch.Tensor,
    advantages: torch.Tensor,
    values: torch.Tensor,
    returns: torch.Tensor,
    clip: float,
    value_coef: float = 1.0,
    entropy: torch.Tensor | None = None,
    entropy_coef: float = 0.0,
    normalize: bool = True,
    value_clip: float | None = None,
    old_values: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The clipped surrogate objective and the value regression, as one loss to minimise.

    Args:
      new_log_prob: [N] log π_θ(a | s) under the policy being optimised (carries the gradient).
      old_log_prob: [N] log π_old(a | s) recorded when acting.
      advantages:   [N] Â (normalised over the minibatch to mean 0, std 1 when `normalize`).
      values:       [N] V_θ(s) (carries the gradient).
      returns:      [N] value targets.
      clip:         ε; the ratio π_θ / π_old is clipped to [1 − ε, 1 + ε].
      value_coef:   weight of the value term.
      entropy:      [N] optional policy entropy; the loss subtracts entropy_coef · mean.
      value_clip:   when given (with old_values [N]), the value may move at most this far
                    from old_values before its error stops being reduced (PPO2's value clipping).

    Terms:
      policy        −mean(min(ρ Â, clip(ρ, 1 − ε, 1 + ε) Â)), ρ = exp(new − old).
      value         ½ mean((V − R)²) (the larger of the clipped and unclipped error with value_clip).
      entropy       mean entropy, when given.
      clip_fraction share of samples with |ρ − 1| > ε.
      approx_kl     mean((ρ − 1) − log ρ), an estimate of KL(π_old ‖ π_θ) that is never negative.
    total = policy + value_coef · value − entropy_coef · entropy. Terms other than total are detached.
    """
    adv = normalize_advantages(advantages.detach()) if normalize else advantages.detach()
    log_ratio = new_log_prob - old_log_prob.detach()
    ratio = torch.exp(log_ratio)
    surrogate = torch.minimum(ratio * adv, torch.clamp(ratio, 1.0 - clip, 1.0 + clip) * adv)
    policy = -surrogate.mean()

    returns = returns.detach()
    value_error = (values - returns) ** 2
    if value_clip is not None:
        if old_values is None:
            raise ValueError("ppo_loss: value_clip needs old_values")
        old_values = old_values.detach()
        clipped = old_values + torch.clamp(values - old_values, -value_clip, value_clip)
        value_error = torch.maximum(value_error, (clipped - returns) ** 2)
    value = 0.5 * value_error.mean()

    total = policy + value_coef * value
    terms: dict[str, torch.Tensor] = {"policy": policy.detach(), "value": value.detach()}
    if entropy is not None:
        mean_entropy = entropy.mean()
        total = total - entropy_coef * mean_entropy
        terms["entropy"] = mean_entropy.detach()
    with torch.no_grad():
        terms["clip_fraction"] = ((ratio - 1.0).abs() > clip).to(ratio.dtype).mean()
        terms["approx_kl"] = ((ratio - 1.0) - log_ratio).mean()
    return total, terms


def action_bound_loss(mean: torch.Tensor, bound: float) -> torch.Tensor:
    """[N, A] policy means -> scalar: mean over samples of Σ_a max(|μ_a| − bound, 0)².

    A soft bound on the action range: zero while every mean lies in [−bound, bound],
    growing quadratically outside. Sampled actions keep their unbounded Gaussian
    (and their log-probabilities); the environment clips what it applies.
    """
    excess = torch.relu(mean.abs() - bound)
    return (excess**2).sum(-1).mean()
