"""One learner per objective on a shared base: its networks and optimiser, `update(batch) -> metrics`,
versioned weights and a state dict."""
