"""fusion: orientation from a gyroscope and an accelerometer, scored against motion capture."""
__version__ = "0.1.0"
