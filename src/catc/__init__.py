"""catc: the pure (sans-I/O) core of the testbench.

Message model and J2735 codecs, geodesy, predictors, the Context-Aware Map,
target classification and the safety applications.  Nothing in this package
opens a socket, starts a thread, or reads a clock.
"""

__version__ = "0.1.0"
