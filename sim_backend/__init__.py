"""Simulated rigs that stand in for hardware: the plain simulator, and protocol peers (a CiA 402
drive on a virtual CAN bus, an Arduino on a pty, the real firmware on simavr) so the real drivers
run in tests."""
