"""Tasks and environments: the Task interface, the three benchmark tasks (each an environment, its supervisor and its
Task), the registry, oracle data sets, evaluation and replay, and the Gymnasium bridge."""
