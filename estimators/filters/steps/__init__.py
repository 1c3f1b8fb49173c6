"""The steps a filter takes each sample (rest and gyro bias, accelerometer, magnetometer, scale
test, stuck gyro), each beside its compiled twin (`_X.py` and `_compiled_X.py`)."""
