"""Real hardware behind ``labbench.device.Device``: the CiA 402 CANopen drive and the serial
encoder stream, with their pure protocol pieces (state machine, EMCY, framing)."""
