"""The batch smoothers (`gn`, `gd`): their shared cost (`cost`), solves (`solve`), magnetometer
stage (`mag`) and estimate (`smoother`), beside their compiled twins (`_compiled_*`)."""
