"""Pure numerics of the laser radar measurement system (no I/O).

SI units everywhere: metres, radians, seconds. Inputs and outputs are numpy arrays.
"""

__version__ = "0.1.0"
