"""The design tool: stability, accuracy and force noise of a device's settings from one model, the Pareto front, the recommended filter, and the check against a campaign's measurements."""
