"""Backends that host the components: in this process (local) or as Ray actors (ray)."""
