"""Built-in plugins (warm start, place recognition, pairwise registration), registered through the
entry-point groups listed in :mod:`dm2_backend.plugins.registry`."""
