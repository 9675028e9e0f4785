"""End-to-end runs: read inputs -> prepare -> optimise (or a baseline) -> write the run folder."""
