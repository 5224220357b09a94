"""The readout: the words and numbers every surface shows (CLI, report, window) from one place, the verdicts, number formats, display units, figures and escaping."""
