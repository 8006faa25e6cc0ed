"""Edge gateway that measures, predicts and compensates spindle thermal error.

`gateway` wires the pieces together: configuration, the command line, and (later)
the per-machine runtime loop. It imports from `models` and `drivers`, never the
other way round.
"""

__version__ = "0.1.0"
