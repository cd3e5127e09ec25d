"""The networks (`torch.nn.Module`s): the world model, the VAE controller and its priors, the discriminator,
the actor-critic, the task policy; `body_state` computes s from body states in torch."""
