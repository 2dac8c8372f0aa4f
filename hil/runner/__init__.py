"""The runner: cell configuration, planners, the safety envelope, the session that procedures run in."""
