"""Losses as pure functions of tensors returning `(total, {name: term})`, one module per objective."""
