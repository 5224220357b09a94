"""The haptic loop and what runs it: the chain (sampled position to command, one sample at a time), the safety envelope, timing and real-time pacing, signals, the runner and its pre-flight checks."""
