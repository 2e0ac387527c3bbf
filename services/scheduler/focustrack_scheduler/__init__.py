"""The scheduler: a scan as a plan of steps (pure) and the engine that runs it."""
