"""The built-in protocols: chirp-ID, white-noise ETFE, stability probe.

Each is a ``labbench.protocol.ProtocolBase``; they are found by name through
``labbench.registry`` (``make_protocol("etfe", ...)``), like those of other packages.
"""
