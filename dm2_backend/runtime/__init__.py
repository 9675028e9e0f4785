"""How dm2 runs, below everything else: its one error type, files written atomically and read with bounds,
progress and stage logs, threads and memory."""
