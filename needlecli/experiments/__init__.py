"""Config schema, input schedules, truth simulation and the experiment runner."""
