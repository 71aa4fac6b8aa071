"""online-id: online identification of engine test-bench drivelines."""

__version__ = "0.1.0"
