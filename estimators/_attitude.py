"""Former home of the recursive filters' helpers, now one module per concern; kept as the list of
where each name went, for the importers outside the filters (`smoother`, `smoother_mag`) until they
import from those modules directly.

`_linalg` (3x3 inverse, PSD square root, covariance repair), `_accel` (accelerometer gating, the
disturbance model, the low-pass and its lag), `_rest` (rest detection, the bias update at rest),
`_stuck` (the online stuck-gyro check), `_scale_test` (Wald's test on the scale factors),
`_magnetometer` (reference field, gates, hard-iron fit, heading update), `_error_state` (the
unestimated variance and axis masks). Their compiled mirrors are `_compiled_<concern>`.
"""
from __future__ import annotations

from ._accel import (AccDisturbance, LowpassLag, acc_measurement, acc_variance_scale, accelerometer_update_input,
                     lowpass_drift_density, lowpass_residual_density, models_lag)
from ._linalg import COV_FLOOR, COV_RESET_VAR, SQRT_FLOOR, inv_sym3, repair_covariance, sqrt_psd
from ._magnetometer import (HARD_IRON_STATE, HardIron, MagReference, field_norm_dip, hard_iron_add, hard_iron_fit,
                            heading_update, heading_variance, magnetometer_input, solve4)
from ._rest import REST_ACC_G, REST_GYR_RAD_S, REST_TIME_S, REST_WINDOW_S, RestDetector, bias_rest_update
from ._scale_test import ScaleTest
from ._stuck import STUCK_STATE, STUCK_THRESHOLDS, stuck_gyro_state, stuck_gyro_update
from ._error_state import UNESTIMATED_VAR, axes_mask

__all__ = ["AccDisturbance", "COV_FLOOR", "COV_RESET_VAR", "HARD_IRON_STATE", "HardIron", "LowpassLag", "MagReference",
           "REST_ACC_G", "REST_GYR_RAD_S", "REST_TIME_S", "REST_WINDOW_S", "RestDetector", "SQRT_FLOOR", "STUCK_STATE",
           "STUCK_THRESHOLDS", "ScaleTest", "UNESTIMATED_VAR", "acc_measurement", "acc_variance_scale",
           "accelerometer_update_input", "axes_mask", "bias_rest_update", "field_norm_dip", "hard_iron_add",
           "hard_iron_fit", "heading_update", "heading_variance", "inv_sym3", "lowpass_drift_density",
           "lowpass_residual_density", "magnetometer_input", "models_lag", "repair_covariance", "solve4", "sqrt_psd",
           "stuck_gyro_state", "stuck_gyro_update"]
