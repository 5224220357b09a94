"""Sessions: the record stream, the crash-safe session file, reading it back, the catalogue of a folder, replay and export."""
