"""Runs over settings: ablations and BROAD's sweep (`ablate`), tuning by one protocol (`tune`),
the gyro calibration's leave-one-out (`loo`)."""
