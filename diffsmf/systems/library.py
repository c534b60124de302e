"""Built-in systems of the seed papers (registered with :func:`diffsmf.systems.register`)."""
