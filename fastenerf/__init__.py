"""fastenerf: radiance fields from a single (colour) event camera, trained fast.

Data flows one way: events -> windows -> rays -> field -> loss -> optimiser.
"""

__version__ = "0.1.0"
