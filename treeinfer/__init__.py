"""treeinfer: learn how tree branches bend when a robot pulls on them."""

__version__ = "0.1.0"
