"""Running the method as jobs: the stage table, config -> parameters, entry points, job plumbing."""
